"""Pictures of a cross-view run, as PNGs in the run dir and in TensorBoard.

- attention.png   MSAE attention over query and reference inputs (the paper's Fig. 6)
- top5.png        each query with its five nearest references (the scorer's top-k: the lower index first among
                  equal scores), framed by relevance (Fig. 9): green a relevant reference (the positive; with
                  labels, any reference of the query's place), orange a semi-positive, red the others
- recall_curve.png  recall@K for K = 1..50 (Fig. 4 style), ranked against the split's relevance, as validation
- TensorBoard projector: the validation descriptors of both views (the t-SNE view of Fig. 8)
"""

from __future__ import annotations

from pathlib import Path
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from geoloc.engine.logging import RunLogger  # noqa: E402
from geoloc.eval.plots import grid, overlay, save_png  # noqa: E402
from geoloc.data.relevance import Relevance  # noqa: E402
from geoloc.eval.recall import recall_summary  # noqa: E402
from geoloc.eval.scoring import rank, top_k  # noqa: E402
from geoloc.tasks.crossview.transforms import normalise  # noqa: E402


def to_uint8(x: torch.Tensor) -> np.ndarray:
    """3×H×W uint8 image (a data module item's) → H×W×3 uint8."""
    return np.ascontiguousarray(x.permute(1, 2, 0).cpu().numpy())


def _frame(img: np.ndarray, color: tuple[int, int, int], t: int = 4) -> np.ndarray:
    out = img.copy()
    out[:t], out[-t:], out[:, :t], out[:, -t:] = color, color, color, color
    return out


GREEN, ORANGE, RED = (0, 200, 0), (240, 150, 0), (220, 0, 0)


def relevance_colour(split, i: int, j: int) -> tuple[int, int, int]:
    """The frame of reference j among query i's retrievals: green for a relevant reference (the split's relevance:
    the positive, or with labels any reference of the query's place), orange for a semi-positive (VIGOR), red
    otherwise."""
    if split is None:
        return GREEN if i == j else RED
    relevance = split.relevance
    if j in relevance.relevant[i]:
        return GREEN
    if relevance.semi_positives is not None and j in relevance.semi_positives[i]:
        return ORANGE
    return RED


def recall_curve(query: torch.Tensor, reference: torch.Tensor, split, kmax: int = 50) -> dict[str, float]:
    """{"R@K": recall} for K = 1..min(kmax, N) (and R@1%), ranked against the split's relevance (one-to-one when
    ``split`` is None): the numbers validation reports, at every K."""
    relevance = Relevance.one_to_one(len(query), len(reference)) if split is None else split.relevance
    ks = range(1, min(kmax, len(reference)) + 1)
    return recall_summary(rank(query, reference, relevance).ranks, ks, len(reference))


def _sides(data):
    """(query image getter, reference image getter, number of queries, of references, split or None): a one-to-one
    CrossViewPairs, or an EvalData whose queries and gallery are apart."""
    pairs = getattr(data, "pairs", None) if hasattr(data, "queries") else data
    if pairs is not None:
        split = getattr(pairs, "split", None)
        return (lambda i: pairs[i]["query"]), (lambda j: pairs[j]["reference"]), len(pairs), len(pairs), (
            None if split is None or split.one_to_one else split)
    return (lambda i: data.queries[i]["image"]), (lambda j: data.references[j]["image"]), len(data.queries), len(
        data.references), data.split


@torch.no_grad()
def crossview_figures(task, data, run_dir: str | Path, device: torch.device, batch_size: int = 64,
                      examples: int = 4, step: int = 0) -> dict[str, Path]:
    """Write the figures for `task` (a CrossViewTask) on `data`: validation CrossViewPairs (one-to-one), or an
    EvalData (geoloc.tasks.crossview.datasets) with queries and gallery apart, whose positives are marked by label."""
    run_dir = Path(run_dir)
    task.eval().to(device)
    query_image, reference_image, n_query, n_reference, split = _sides(data)
    query_branch, reference_branch = task.model.encoders(split is not None and split.aerial_queries)

    def encode(branch, image, n):
        out = []
        for start in range(0, n, batch_size):
            batch = torch.stack([image(i) for i in range(start, min(start + batch_size, n))]).to(device)
            out.append(branch(normalise(batch)).float().cpu())
        return torch.cat(out)

    query, reference = encode(query_branch, query_image, n_query), encode(reference_branch, reference_image, n_reference)
    positive = (lambda i: i) if split is None else (lambda i: int(split.positives[i]))
    logger = RunLogger(run_dir)
    paths = {}

    # attention maps: each example query and its positive reference
    picks = list(range(min(examples, n_query)))
    rows = []
    for i in picks:
        q, r = query_image(i), reference_image(positive(i))
        _, q_mask = query_branch(normalise(q[None].to(device)), return_attention=True)
        _, r_mask = reference_branch(normalise(r[None].to(device)), return_attention=True)
        q_img, r_img = to_uint8(q), to_uint8(r)
        rows.append([q_img, overlay(q_img, q_mask[0]), r_img, overlay(r_img, r_mask[0])])
    paths["attention"] = run_dir / "attention.png"
    save_png(paths["attention"], grid(rows))
    logger.image("figures/attention", grid(rows), step)

    # top-5 retrievals, framed by relevance
    rows = []
    _, tops = top_k(query[picks], reference, 5)
    for row, i in enumerate(picks):
        top = tops[row].tolist()
        tiles = [to_uint8(query_image(i))]
        for j in top:
            tiles.append(_frame(to_uint8(reference_image(j)), relevance_colour(split, i, j)))
        rows.append(tiles)
    paths["top5"] = run_dir / "top5.png"
    save_png(paths["top5"], grid(rows))
    logger.image("figures/top5", grid(rows), step)

    # recall curve
    kmax = min(50, n_reference)
    recall = recall_curve(query, reference, split, kmax)
    fig, ax = plt.subplots(figsize=(4.5, 3.2), dpi=120)
    ax.plot(range(1, kmax + 1), [100 * recall[f"R@{k}"] for k in range(1, kmax + 1)], marker=".")
    ax.set_xlabel("K")
    ax.set_ylabel("recall@K (%)")
    ax.set_title(f"recall@K, {n_query} queries, {n_reference} references")
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
