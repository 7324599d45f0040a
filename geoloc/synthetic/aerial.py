"""Orthographic top-down tile: north up, east right, the place's camera at the exact centre (or any square of
cells, for tiles off the world's centre)."""
from __future__ import annotations

import cv2
import numpy as np

from .appearance import apply_season
from .light import Lighting
from .world import World


def tile_slice(world: World, tile_m: float) -> slice:
    """The centred square of cells covering tile_m metres (both counts are even, so the centre is exact)."""
    t = int(round(tile_m / world.cell))
    if t % 2 or world.n % 2 or t > world.n:
        raise ValueError(f"tile of {t} cells must be even and fit the {world.n}-cell world")
    lo = (world.n - t) // 2
    return slice(lo, lo + t)


def render_aerial(world: World, light: Lighting, tile_m: float, size: int, season: float,
                  class_gains: np.ndarray | None = None):
    """-> (rgb float size x size x 3 in [0, 1], class map size x size uint8). class_gains: see
    render_aerial_window."""
    sl = tile_slice(world, tile_m)
    return render_aerial_window(world, light, sl, sl, size, season, class_gains)


def render_aerial_window(world: World, light: Lighting, rows: slice, cols: slice, size: int, season: float,
                         class_gains: np.ndarray | None = None):
    """The square of cells [rows, cols] (any place in the world: the vigor layout's overlapping tiles) -> (rgb float
    size x size x 3 in [0, 1], class map size x size uint8). class_gains (classes x 3): each class's albedo times
    its RGB gain (nuisance.py's per-view materials); None leaves it."""
    cls = world.cls[rows, cols]
    albedo = world.top[rows, cols].astype(np.float32) * (1.0 / 255.0)
    albedo = apply_season(albedo, cls, season)
    if class_gains is not None:
        albedo *= class_gains[cls]
    rgb = albedo * light.top_shade_block(rows, cols)[..., None]
    t = cls.shape[0]
    interp = cv2.INTER_AREA if size < t else cv2.INTER_LINEAR
    rgb = cv2.resize(rgb, (size, size), interpolation=interp)
    cls_out = cv2.resize(cls, (size, size), interpolation=cv2.INTER_NEAREST)
    return rgb, cls_out
