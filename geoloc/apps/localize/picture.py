"""The picture of one localisation: the query, its top-k tiles, and a map of the candidates.

When the answer is refined inside the tile, the top-1 tile carries the refiner's probability map, the refined
position (a dot) and its heading (an arrow, clockwise from north = up).

Tiles are framed green when they are the query's true reference (known when the image is one of the gallery
split's queries), red otherwise. The map shows the neighbourhood of the true position (of the top-1 when it is
unknown) in metres: the gallery's references there (grey), the top-k that fall in it (numbered, the top-1 largest)
and the true position (a star), titled with the top-1 metre error.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from geoloc.data.geo import latlon_to_offset  # noqa: E402
from geoloc.gallery import POSITION_KEYS, LocalizationResult  # noqa: E402

MAP_POINTS = 20_000  # grey gallery points drawn at most (a 1M gallery is subsampled)
NEIGHBOURHOOD_M = 5_000.0  # the map shows candidates this close to its centre
MIN_RADIUS_M = 150.0


def _refined(ax, answer: LocalizationResult, hit: dict, tile: np.ndarray) -> None:
    """On the top-1 tile: the refiner's probability map, its position (a dot) and heading (an arrow)."""
    height, width = tile.shape[:2]
    prob = answer.probability_map
    ax.imshow(prob / max(float(prob.max()), 1e-12), extent=(0, width, height, 0), cmap="magma", alpha=0.5,
              interpolation="bilinear")
    refined = hit["refined_position"]
    (row, col), (size_h, size_w) = refined["tile_px"], refined["tile_size_px"]  # the localizer's pixel of it
    row, col = row * height / size_h, col * width / size_w
    angle = np.radians(refined["heading_deg"])
    length = 0.15 * width
    ax.scatter([col], [row], s=40, c="cyan", edgecolors="k", zorder=3)
    ax.annotate("", xy=(col + length * np.sin(angle), row - length * np.cos(angle)), xytext=(col, row),
                arrowprops=dict(arrowstyle="->", color="cyan", lw=2))


def _array(kind: str, where: dict) -> np.ndarray:
    return np.array([where[k] for k in POSITION_KEYS[kind]], np.float64)


def _metres(kind: str, centre: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(..., 2) east / north metres of points from centre (positions of `kind`)."""
    if kind == "latlon":
        return latlon_to_offset(centre, points)
    return np.asarray(points, np.float64) - centre


def _candidate_map(ax, answer: LocalizationResult, places) -> None:
    """The neighbourhood of the true position (or of the top-1 when the truth is unknown), in metres: the gallery's
    references there, the top-k that fall in it, the true position; candidates elsewhere are counted in the title
    (a same-area VIGOR gallery spans four cities)."""
    kind, truth, topk = places.kind, answer.truth or {}, answer.topk
    centre = _array(kind, truth["position"]) if "position" in truth else _array(kind, topk[0])
    hits = np.stack([_metres(kind, centre, _array(kind, hit)) for hit in topk])
    near = np.linalg.norm(hits, axis=1) <= NEIGHBOURHOOD_M
    radius = max(MIN_RADIUS_M, 1.2 * float(np.abs(hits[near]).max(initial=0.0)))
    gallery = _metres(kind, centre, places.reference_positions)
    shown = gallery[(np.abs(gallery) <= radius).all(axis=1)]
    if len(shown) > MAP_POINTS:
        shown = shown[np.random.default_rng(0).choice(len(shown), MAP_POINTS, replace=False)]
    ax.scatter(shown[:, 0], shown[:, 1], s=6, c="lightgrey", label="gallery tiles")
    for hit, (x, y), inside in reversed(list(zip(topk, hits, near))):
        if inside:
            first = hit["rank"] == 1
            ax.scatter([x], [y], s=90 if first else 40, c="tab:blue" if first else "tab:cyan", edgecolors="k",
                       zorder=3, label="top-1" if first else None)
            ax.annotate(str(hit["rank"]), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    title = "candidates"
    if "position" in truth:
        ax.scatter([0], [0], marker="*", s=220, c="gold", edgecolors="k", zorder=4, label="true position")
        title = f"top-1 error {truth['error_m']:,.0f} m"
    if (~near).any():
        title += f"\n{int((~near).sum())} of the top-{len(topk)} more than {NEIGHBOURHOOD_M / 1000:.0f} km away"
    ax.set_title(title, fontsize=9)
    ax.set_xlim(-radius, radius)
    ax.set_ylim(-radius, radius)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal")
    ax.legend(fontsize=7, loc="upper right")


def localization_figure(answer: LocalizationResult, image: np.ndarray, places, out: Path) -> Path:
    """Write `out` (PNG) for a Localizer answer about `image` (H×W×3 uint8)."""
    topk = answer.topk
    truth = answer.truth or {}
    has_map = places.kind is not None
    cols = len(topk) + (2 if has_map else 0)
    fig = plt.figure(figsize=(2.2 * cols + 2, 5.2))
    grid = fig.add_gridspec(2, cols, height_ratios=[1.1, 1])
    ax = fig.add_subplot(grid[0, : cols - (2 if has_map else 0)])
    ax.imshow(image)
    heading = f"heading {answer.heading_deg:.0f}° ({answer.heading_source})"
    ax.set_title(f"{Path(str(answer.image or 'query')).name}  fov {answer.fov_deg:.0f}°  {heading}", fontsize=9)
    ax.axis("off")
    for i, hit in enumerate(topk):
        ax = fig.add_subplot(grid[1, i])
        tile = places.tile_image(hit["path"])
        if tile is not None:
            ax.imshow(tile)
            if i == 0 and answer.probability_map is not None and "refined_position" in hit:
                _refined(ax, answer, hit, tile)
        colour = "green" if hit["row"] == truth.get("row") else "red" if truth else "grey"
        for side in ax.spines.values():
            side.set_edgecolor(colour)
            side.set_linewidth(3)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"#{hit['rank']}  {hit['score']:.3f}\n{hit['heading_deg']:.0f}°", fontsize=8)
    if has_map:
        _candidate_map(fig.add_subplot(grid[:, cols - 2:]), answer, places)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
