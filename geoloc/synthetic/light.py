"""Sun light: surface normals from the height field, cast shadows by height-field marching, Lambert shading.

Shading is evaluated lazily, only at the cells a view actually looks at (a panorama sees a few hundred thousand
of the world's cells, an aerial tile only its own square), so a world with another sun costs little.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .world import World


@dataclass(frozen=True)
class Sun:
    azimuth: float  # compass bearing of the sun, degrees clockwise from north
    elevation: float  # degrees above the horizon
    ambient: float = 0.5
    direct: float = 0.7

    def vector(self) -> np.ndarray:
        """Unit vector towards the sun, (east, north, up)."""
        a, e = np.deg2rad(self.azimuth), np.deg2rad(self.elevation)
        return np.array([np.sin(a) * np.cos(e), np.cos(a) * np.cos(e), np.sin(e)], np.float32)


class Lighting:
    """One world under one sun. All lookups take flat cell indices (row * N + col)."""

    def __init__(self, world: World, sun: Sun, shadow_cell: float = 1.0):
        self.world, self.sun = world, sun
        self.f = max(1, int(round(shadow_cell / world.cell)))
        self.shadow_h = shadow_heights(world, sun, self.f)
        self._full = None

    def _gradient(self, idx: np.ndarray):
        """Central differences of the (static) height field at the cells: (d/deast, d/dnorth).
        Neighbours are idx +- 1 and idx +- N, clamped to the grid (views never look at its outermost cells)."""
        n, h = self.world.n, self.world.static.height.ravel()
        last = h.size - 1
        k = np.float32(0.5 / self.world.cell)
        gx = (h[np.minimum(idx + 1, last)] - h[np.maximum(idx - 1, 0)]) * k
        gy = (h[np.maximum(idx - n, 0)] - h[np.minimum(idx + n, last)]) * k
        return gx, gy

    def _shadow_full(self) -> np.ndarray:
        """The coarse shadow heights bilinearly upsampled to the fine grid (computed once, on first use)."""
        if self._full is None:
            m, n = self.shadow_h.shape[0], self.world.n
            full = cv2.resize(self.shadow_h, (m * self.f, m * self.f), interpolation=cv2.INTER_LINEAR)
            if full.shape[0] < n:
                full = np.pad(full, ((0, n - full.shape[0]), (0, n - full.shape[1])), mode="edge")
            self._full = full
        return self._full

    def lit(self, idx: np.ndarray) -> np.ndarray:
        """1 where the cell's surface sees the sun, 0 in cast shadow, soft over ~0.35 m of height."""
        sh = self._shadow_full().ravel()[idx]
        return np.minimum(np.maximum((self.world.height.ravel()[idx] - sh) * np.float32(1 / 0.35) + 0.5, 0), 1)

    def top_shade(self, idx: np.ndarray) -> np.ndarray:
        """ambient + direct * lit * max(0, n . sun) for the upward surface; wall-edge cells count as flat."""
        gx, gy = self._gradient(idx)
        steep = (gx * gx + gy * gy) > 4.0
        nx, ny = np.where(steep, 0, -gx), np.where(steep, 0, -gy)
        s = self.sun.vector()
        cos = (nx * s[0] + ny * s[1] + s[2]) / np.sqrt(nx * nx + ny * ny + 1.0)
        return (self.sun.ambient + self.sun.direct * self.lit(idx) * np.maximum(cos, 0)).astype(np.float32)

    def top_shade_block(self, rows: slice, cols: slice) -> np.ndarray:
        """top_shade over a rectangle of cells, by array slicing (the aerial tile)."""
        w = self.world
        h = np.pad(w.static.height, 1, mode="edge")[rows.start : rows.stop + 2, cols.start : cols.stop + 2]
        k = np.float32(0.5 / w.cell)
        gx = (h[1:-1, 2:] - h[1:-1, :-2]) * k
        gy = (h[:-2, 1:-1] - h[2:, 1:-1]) * k
        steep = (gx * gx + gy * gy) > 4.0
        nx, ny = np.where(steep, 0, -gx), np.where(steep, 0, -gy)
        s = self.sun.vector()
        cos = (nx * s[0] + ny * s[1] + s[2]) / np.sqrt(nx * nx + ny * ny + 1.0)
        full = self._shadow_full()
        lit = np.clip((w.height[rows, cols] - full[rows, cols]) / 0.35 + 0.5, 0.0, 1.0)
        return (self.sun.ambient + self.sun.direct * lit * np.maximum(cos, 0)).astype(np.float32)

    def wall_normal(self, idx: np.ndarray):
        """Horizontal outward normal (east, north) of a height step at the cells; (0, 0) where it is flat."""
        gx, gy = self._gradient(idx)
        g2 = gx * gx + gy * gy
        inv = np.where(g2 > 0.25, 1.0 / np.sqrt(g2 + 1e-12), 0.0).astype(np.float32)
        return -gx * inv, -gy * inv


def shadow_heights(world: World, sun: Sun, f: int) -> np.ndarray:
    """Per coarse cell (f x f fine cells, max-pooled): the height below which a point there is in cast shadow.

    That is max over steps t of H(p + t*sun) - t*tan(elevation). Comparing it with the fine height keeps shadows
    monotone: adding an object (a car) only ever darkens other cells.
    """
    n = world.n // f * f
    h = world.height[:n, :n]
    cols = h[:, 0::f]
    for i in range(1, f):  # strided slices: much faster than a reshape + max over two axes
        cols = np.maximum(cols, h[:, i::f])
    h = cols[0::f]
    for i in range(1, f):
        h = np.maximum(h, cols[i::f])
    m = h.shape[0]
    tan_e = np.tan(np.deg2rad(max(sun.elevation, 3.0)))
    s = sun.vector()
    step = np.array([s[0], -s[1]]) / max(abs(s[0]), abs(s[1]))  # (dcol, drow) per coarse step
    step_len = world.cell * f * np.hypot(*step)
    hmax = float(h.max())
    out = np.full((m, m), -1.0, np.float32)
    k = 1
    while hmax - k * step_len * tan_e > 0.05 and k < m:
        dc, dr = int(round(k * step[0])), int(round(k * step[1]))
        src = h[max(0, dr) : m + min(0, dr), max(0, dc) : m + min(0, dc)]
        dst = out[max(0, -dr) : m + min(0, -dr), max(0, -dc) : m + min(0, -dc)]
        np.maximum(dst, src - k * step_len * tan_e, out=dst)
        k += 1
    return out
