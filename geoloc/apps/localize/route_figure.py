"""The picture of a route (out/route.png): the gallery's tiles near it, each frame's own answer, the filtered track
with its 95% covariance ellipses, and the truth where the route folder gives one (truth.csv)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

ELLIPSE_CHI2_95 = 5.991  # the chi-square 95% quantile with 2 degrees of freedom


def route_figure(plane, estimates, answers, truth: np.ndarray | None, path: Path) -> Path:
    """Draw the route on the filter's plane, in metres east and north of the track's first point, zoomed to the
    track and the truth: `estimates` and `answers` (FrameAnswer: each frame's top-1, refined where it was) per
    frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    origin = np.asarray(estimates[0].position, np.float64)
    track = np.stack([e.position for e in estimates]) - origin
    answers = np.stack([a.centres[0] if a.refined is None else a.refined[0] for a in answers]) - origin
    tiles = plane.tiles - origin
    truth = None if truth is None else truth - origin
    shown = [track] + ([truth] if truth is not None else [])
    low, high = np.min([p.min(0) for p in shown], 0) - 60, np.max([p.max(0) for p in shown], 0) + 60
    fig, ax = plt.subplots(figsize=(7, 7))
    near = ((tiles >= low) & (tiles <= high)).all(1)
    ax.scatter(*tiles[near].T, s=8, c="0.8", marker="s", label="gallery tiles")
    inside = ((answers >= low) & (answers <= high)).all(1)
    ax.scatter(*answers[inside].T, s=14, c="tab:orange", label=f"frame answers ({inside.sum()} of {len(answers)} "
                                                               "in view)")
    if truth is not None:
        ax.plot(*truth.T, "-o", c="tab:green", ms=3, label="truth (star: the last frame)")
        ax.scatter(*truth[-1], s=90, c="tab:green", marker="*", zorder=6)
    ax.plot(*track.T, "-", c="tab:blue", lw=1.5, label="filtered track")
    for estimate in estimates:
        _ellipse(ax, estimate.mean - origin, estimate.covariance)
    ax.scatter(*track[-1], s=40, c="tab:blue", zorder=5)  # the last frame's estimate
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_aspect("equal")
    ax.set_xlabel("east of the first estimate (m)")
    ax.set_ylabel("north (m)")
    ax.set_title("route: frame answers, filtered track and 95% covariance ellipses")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _ellipse(ax, mean, covariance) -> None:
    values, vectors = np.linalg.eigh(np.asarray(covariance, np.float64) + 1e-9 * np.eye(2))
    angle = np.linspace(0, 2 * np.pi, 60)
    circle = np.stack([np.cos(angle), np.sin(angle)])
    points = (vectors @ (np.sqrt(ELLIPSE_CHI2_95 * np.maximum(values, 0))[:, None] * circle)).T + mean
    ax.plot(*points.T, c="tab:blue", lw=0.5, alpha=0.4)
