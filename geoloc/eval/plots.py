"""Picture building blocks every figure shares: image grids, heat-map overlays, PNG writing (RGB arrays)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch


def overlay(img: np.ndarray, mask: torch.Tensor) -> np.ndarray:
    m = mask.detach().float().cpu().numpy().squeeze()
    m = (m - m.min()) / (np.ptp(m) + 1e-8)
    heat = cv2.applyColorMap(cv2.resize((m * 255).astype(np.uint8), img.shape[1::-1]), cv2.COLORMAP_JET)
    return cv2.addWeighted(img, 0.55, cv2.cvtColor(heat, cv2.COLOR_BGR2RGB), 0.45, 0)


def fit_height(img: np.ndarray, h: int) -> np.ndarray:
    return cv2.resize(img, (max(1, round(img.shape[1] * h / img.shape[0])), h))


def grid(rows: list[list[np.ndarray]], h: int = 128, pad: int = 4) -> np.ndarray:
    lines = []
    for row in rows:
        tiles = [np.pad(fit_height(t, h), ((pad, pad), (pad, pad), (0, 0)), constant_values=255) for t in row]
        lines.append(np.concatenate(tiles, axis=1))
    width = max(line.shape[1] for line in lines)
    lines = [np.pad(line, ((0, 0), (0, width - line.shape[1]), (0, 0)), constant_values=255) for line in lines]
    return np.concatenate(lines, axis=0)


def save_png(path: Path, img: np.ndarray) -> None:
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))


def confidence_figure(path: Path, probability: np.ndarray, right: np.ndarray, ece: float, coverage: np.ndarray,
                      accuracy: np.ndarray, bins: int = 15) -> Path:
    """confidence.png: the reliability diagram (accuracy against mean confidence in `bins` equal-count bins) beside
    the coverage-accuracy curve (the most confident answers kept first)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = np.argsort(probability, kind="stable")
    runs = [r for r in np.array_split(order, min(bins, len(order))) if len(r)]
    fig, (left, right_ax) = plt.subplots(1, 2, figsize=(9, 4))
    left.plot([0, 1], [0, 1], color="grey", lw=0.8, ls="--", label="calibrated")
    left.plot([probability[r].mean() for r in runs], [right[r].mean() for r in runs], "o-", label="bins")
    left.set(xlabel="mean confidence", ylabel="accuracy", xlim=(0, 1), ylim=(0, 1),
             title=f"reliability, ECE {ece:.3f} ({len(probability)} queries)")
    left.legend(loc="upper left")
    right_ax.plot(coverage, accuracy)
    right_ax.set(xlabel="coverage (share of answers kept)", ylabel="accuracy of the kept answers", xlim=(0, 1),
                 ylim=(0, 1.02), title="coverage-accuracy")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
