"""Pictures of a cross-view run, as PNGs in the run dir and in TensorBoard.

- attention.png   MSAE attention over query and reference inputs (the paper's Fig. 6)
- top5.png        each query with its five nearest references, the true match framed green (Fig. 9)
- recall_curve.png  recall@K for K = 1..50 (Fig. 4 style)
- TensorBoard projector: the validation descriptors of both views (the t-SNE view of Fig. 8)
"""

from __future__ import annotations

from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from geoloc.data.crossview import IMAGENET_MEAN, IMAGENET_STD  # noqa: E402
from geoloc.engine.logging import RunLogger  # noqa: E402
from geoloc.eval.recall import recall_at_k  # noqa: E402


def to_uint8(x: torch.Tensor) -> np.ndarray:
    """3×H×W normalised tensor → H×W×3 uint8."""
    img = x.detach().float().cpu().numpy().transpose(1, 2, 0) * IMAGENET_STD + IMAGENET_MEAN
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def overlay(img: np.ndarray, mask: torch.Tensor) -> np.ndarray:
    m = mask.detach().float().cpu().numpy().squeeze()
    m = (m - m.min()) / (np.ptp(m) + 1e-8)
    heat = cv2.applyColorMap(cv2.resize((m * 255).astype(np.uint8), img.shape[1::-1]), cv2.COLORMAP_JET)
    return cv2.addWeighted(img, 0.55, cv2.cvtColor(heat, cv2.COLOR_BGR2RGB), 0.45, 0)


def _fit(img: np.ndarray, h: int) -> np.ndarray:
    return cv2.resize(img, (max(1, round(img.shape[1] * h / img.shape[0])), h))


def _frame(img: np.ndarray, color: tuple[int, int, int], t: int = 4) -> np.ndarray:
    out = img.copy()
    out[:t], out[-t:], out[:, :t], out[:, -t:] = color, color, color, color
    return out


def _grid(rows: list[list[np.ndarray]], h: int = 128, pad: int = 4) -> np.ndarray:
    lines = []
    for row in rows:
        tiles = [np.pad(_fit(t, h), ((pad, pad), (pad, pad), (0, 0)), constant_values=255) for t in row]
        lines.append(np.concatenate(tiles, axis=1))
    width = max(line.shape[1] for line in lines)
    lines = [np.pad(line, ((0, 0), (0, width - line.shape[1]), (0, 0)), constant_values=255) for line in lines]
    return np.concatenate(lines, axis=0)


def _save(path: Path, img: np.ndarray) -> None:
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))


@torch.no_grad()
def crossview_figures(task, dataset, run_dir: str | Path, device: torch.device, batch_size: int = 64,
                      examples: int = 4, step: int = 0) -> dict[str, Path]:
    """Write the figures for `task` (a CrossViewTask) on `dataset` (a validation CrossViewPairs)."""
    run_dir = Path(run_dir)
    task.eval().to(device)
    queries, references = [], []
    for start in range(0, len(dataset), batch_size):
        items = [dataset[i] for i in range(start, min(start + batch_size, len(dataset)))]
        q = torch.stack([it["query"] for it in items]).to(device)
        r = torch.stack([it["reference"] for it in items]).to(device)
        queries.append(task.model.query(q).float().cpu())
        references.append(task.model.reference(r).float().cpu())
    query, reference = torch.cat(queries), torch.cat(references)
    logger = RunLogger(run_dir)
    paths = {}

    # attention maps
    picks = list(range(min(examples, len(dataset))))
    rows = []
    for i in picks:
        item = dataset[i]
        _, q_mask = task.model.query(item["query"][None].to(device), return_attention=True)
        _, r_mask = task.model.reference(item["reference"][None].to(device), return_attention=True)
        q_img, r_img = to_uint8(item["query"]), to_uint8(item["reference"])
        rows.append([q_img, overlay(q_img, q_mask[0]), r_img, overlay(r_img, r_mask[0])])
    paths["attention"] = run_dir / "attention.png"
    _save(paths["attention"], _grid(rows))
    logger.image("figures/attention", _grid(rows), step)

    # top-5 retrievals
    rows = []
    sim = query[picks] @ reference.T
    for row, i in enumerate(picks):
        top = torch.topk(sim[row], k=min(5, len(dataset))).indices.tolist()
        tiles = [to_uint8(dataset[i]["query"])]
        for j in top:
            ref = to_uint8(dataset[j]["reference"])
            tiles.append(_frame(ref, (0, 200, 0) if j == i else (220, 0, 0)))
        rows.append(tiles)
    paths["top5"] = run_dir / "top5.png"
    _save(paths["top5"], _grid(rows))
    logger.image("figures/top5", _grid(rows), step)

    # recall curve
    kmax = min(50, len(dataset))
    recall = recall_at_k(query, reference, ks=tuple(range(1, kmax + 1)))
    fig, ax = plt.subplots(figsize=(4.5, 3.2), dpi=120)
    ax.plot(range(1, kmax + 1), [100 * recall[f"R@{k}"] for k in range(1, kmax + 1)], marker=".")
    ax.set_xlabel("K")
    ax.set_ylabel("recall@K (%)")
    ax.set_title(f"recall@K, {len(dataset)} queries")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    paths["recall_curve"] = run_dir / "recall_curve.png"
    fig.savefig(paths["recall_curve"])
    plt.close(fig)

    # descriptors for TensorBoard's projector (PCA / t-SNE)
    labels = [f"query {i}" for i in range(len(query))] + [f"reference {i}" for i in range(len(reference))]
    logger.embedding("descriptors", torch.cat([query, reference]), labels, step)
    logger.close()
    return paths
