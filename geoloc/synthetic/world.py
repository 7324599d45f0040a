"""The 2.5D world of one place: a height field plus per-cell class and colour maps.

Coordinates are metres, x east and y north, with the origin at the centre of the grid (the place's camera).
Cell (row, col) covers x in [col*c - E/2, (col+1)*c - E/2) and y in (E/2 - (row+1)*c, E/2 - row*c], so rows
grow southward and an aerial crop of the grid is north-up, east-right as is.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


_SHIFT = 4  # cv2 fixed-point bits: polygons are drawn with 1/16-cell precision
_ONE = 1 << _SHIFT


@dataclass
class World:
    """Per-cell arrays, all N x N (colours N x N x 3 uint8).

    height: metres above the flat ground; cls: static class 0..7 (8/9 once traffic is stamped in);
    top: albedo of the upward-facing surface; wall: albedo of the vertical faces (building facades, tree sides).
    """

    cell: float
    height: np.ndarray
    cls: np.ndarray
    top: np.ndarray
    wall: np.ndarray
    # The static world a traffic-stamped copy was made from. Surface normals and ground texture are read from it,
    # so adding a car changes only the pixels that see the car, or its shadow.
    base: "World | None" = None

    @classmethod
    def empty(cls, extent: float, cell: float, ground_rgb, ground_cls: int = 0) -> "World":
        n = int(round(extent / cell))
        row = np.tile(np.asarray(ground_rgb, np.uint8), n)  # tiling a contiguous row beats a broadcast copy
        return cls(
            cell=cell,
            height=np.zeros((n, n), np.float32),
            cls=np.full((n, n), ground_cls, np.uint8),
            top=np.tile(row, n).reshape(n, n, 3),
            wall=np.tile(row, n).reshape(n, n, 3),
        )

    @property
    def n(self) -> int:
        return self.height.shape[0]

    @property
    def extent(self) -> float:
        return self.n * self.cell

    def contains(self, x: float, y: float, margin: float = 0.0) -> bool:
        """Whether (x, y) lies within margin metres of the world square."""
        half = self.extent / 2 + margin
        return -half < x < half and -half < y < half

    def copy(self) -> "World":
        return World(self.cell, self.height.copy(), self.cls.copy(), self.top.copy(), self.wall.copy())

    @property
    def static(self) -> "World":
        return self if self.base is None else self.base

    # -- coordinate helpers -------------------------------------------------------------------------------
    def to_cell(self, x, y):
        """Metres -> fractional (col, row) in cell units (cell centres sit at .5)."""
        half = self.extent / 2
        return (np.asarray(x) + half) / self.cell, (half - np.asarray(y)) / self.cell

    def cell_index(self, x, y):
        """Metres -> (flat index into the N*N arrays, inside mask)."""
        col, row = self.to_cell(x, y)
        col = np.floor(col).astype(np.int64)
        row = np.floor(row).astype(np.int64)
        inside = (col >= 0) & (col < self.n) & (row >= 0) & (row < self.n)
        return np.clip(row, 0, self.n - 1) * self.n + np.clip(col, 0, self.n - 1), inside

    def _pts(self, xy) -> np.ndarray:
        col, row = self.to_cell(np.asarray(xy)[:, 0], np.asarray(xy)[:, 1])
        return np.round(np.stack([col, row], 1) * _ONE).astype(np.int32)

    # -- flat drawing (ground-level classes: roads, markings, fields, lawns) ----------------------------------
    def fill_polygon(self, xy, cls: int, rgb, height: float | None = None) -> None:
        pts = [self._pts(xy)]
        cv2.fillPoly(self.cls, pts, int(cls), cv2.LINE_8, _SHIFT)
        cv2.fillPoly(self.top, pts, tuple(int(v) for v in rgb), cv2.LINE_8, _SHIFT)
        cv2.fillPoly(self.wall, pts, tuple(int(v) for v in rgb), cv2.LINE_8, _SHIFT)
        if height is not None:
            cv2.fillPoly(self.height, pts, float(height), cv2.LINE_8, _SHIFT)

    def draw_polyline(self, xy, width: float, cls: int, rgb, height: float | None = None) -> None:
        """A strip of the given width (metres) along a polyline; round joints keep curves closed."""
        self.draw_polylines([xy], width, cls, rgb, height)

    def draw_polylines(self, lines, width: float, cls: int, rgb, height: float | None = None) -> None:
        """Many strips of one material in one cv2 call per layer (dashes, zebra stripes, crop rows)."""
        if not len(lines):
            return
        if isinstance(lines, np.ndarray) and lines.ndim == 3:  # equal-length lines in one array
            pts = list(self._pts(lines.reshape(-1, 2)).reshape(lines.shape[0], -1, 2))
        else:
            lines = [np.asarray(xy, float) for xy in lines]
            allpts = self._pts(np.concatenate(lines))
            pts = np.split(allpts, np.cumsum([len(xy) for xy in lines])[:-1])
        thick = max(1, int(round(width / self.cell)))
        col = tuple(int(v) for v in rgb)
        cv2.polylines(self.cls, pts, False, int(cls), thick, cv2.LINE_8, _SHIFT)
        cv2.polylines(self.top, pts, False, col, thick, cv2.LINE_8, _SHIFT)
        cv2.polylines(self.wall, pts, False, col, thick, cv2.LINE_8, _SHIFT)
        if height is not None:
            cv2.polylines(self.height, pts, False, float(height), thick, cv2.LINE_8, _SHIFT)

    # -- raised objects (buildings, trees, vehicles) -------------------------------------------------------
    def _patch(self, x: float, y: float, radius: float):
        """Slices and local metre coordinates (dx east, dy north) of the cells within radius of (x, y)."""
        c, half = self.cell, self.extent / 2
        col, row = (x + half) / c, (half - y) / c
        r = radius / c + 1
        c0, c1 = max(0, int(col - r)), min(self.n, int(col + r) + 1)
        r0, r1 = max(0, int(row - r)), min(self.n, int(row + r) + 1)
        if c0 >= c1 or r0 >= r1:
            return None
        dx = (np.arange(c0, c1, dtype=np.float32) + np.float32(0.5 - col)) * np.float32(c)
        dy = (np.arange(r0, r1, dtype=np.float32) + np.float32(0.5 - row)) * np.float32(-c)
        return (slice(r0, r1), slice(c0, c1)), dx[None, :], dy[:, None]

    def stamp_box(self, x, y, length, width, angle, h_wall, h_roof, cls, roof_rgb, wall_rgb,
                  ridge_along: bool = True) -> None:
        """A rotated box (angle: compass bearing of its long axis, degrees) with an optional gable roof.

        The roof rises linearly from h_wall at the eaves to h_wall + h_roof at the ridge, so the height field's
        gradient gives the two roof planes their own sun shading.
        """
        p = self._patch(x, y, 0.5 * float(np.hypot(length, width)))
        if p is None:
            return
        sl, dx, dy = p
        a = np.deg2rad(angle)
        u = dx * np.sin(a) + dy * np.cos(a)  # along the long axis
        v = dx * np.cos(a) - dy * np.sin(a)  # across
        inside = (np.abs(u) <= length / 2) & (np.abs(v) <= width / 2)
        if not inside.any():
            return
        across = np.abs(v) / (width / 2) if ridge_along else np.abs(u) / (length / 2)
        h = (h_wall + h_roof * (1.0 - np.minimum(across, 1))).astype(np.float32)
        self._write(sl, inside, h, cls, roof_rgb, wall_rgb)

    def stamp_column(self, x: float, y: float, height: float, cls: int, top_rgb, wall_rgb) -> None:
        """A one-cell column (a pole): much cheaper than a box."""
        col, row = self.to_cell(x, y)
        r, c = int(row), int(col)
        if 0 <= r < self.n and 0 <= c < self.n and height >= self.height[r, c]:
            self.height[r, c] = height
            self.cls[r, c] = cls
            self.top[r, c] = top_rgb
            self.wall[r, c] = wall_rgb

    def stamp_vehicle(self, x, y, length, width, angle, cls, rgb, glass_rgb) -> None:
        """A car in one stamp: a 0.85 m body box with a 1.45 m glass cabin over its rear-middle half."""
        p = self._patch(x, y, 0.5 * float(np.hypot(length, width)))
        if p is None:
            return
        sl, dx, dy = p
        a = np.deg2rad(angle)
        u = dx * np.float32(np.sin(a)) + dy * np.float32(np.cos(a))
        v = dx * np.float32(np.cos(a)) - dy * np.float32(np.sin(a))
        inside = (np.abs(u) <= length / 2) & (np.abs(v) <= width / 2)
        cabin = inside & (np.abs(u + 0.2 * length) <= 0.25 * length) & (np.abs(v) <= 0.45 * width)
        h = np.where(cabin, np.float32(1.45), np.float32(0.85))
        wall = np.where(cabin[..., None], np.asarray(glass_rgb, np.uint8), np.asarray(rgb, np.uint8))
        self._write(sl, inside, h, cls, rgb, wall)

    def stamp_dome(self, x, y, radius, h_base, h_crown, cls, rgb, wall_rgb=None) -> None:
        """A round crown (tree, bush): height h_base + h_crown*sqrt(1-(r/R)^2)."""
        p = self._patch(x, y, radius)
        if p is None:
            return
        sl, dx, dy = p
        q = (dx * dx + dy * dy) / (radius * radius)
        inside = q <= 1.0
        if not inside.any():
            return
        h = (h_base + h_crown * np.sqrt(np.maximum(1.0 - q, 0))).astype(np.float32)
        self._write(sl, inside, h, cls, rgb, rgb if wall_rgb is None else wall_rgb)

    def _write(self, sl, inside, h, cls, top_rgb, wall_rgb) -> None:
        # Only raise the height field: a lower object drawn later never cuts into a taller one.
        cur = self.height[sl]
        take = inside & (h >= cur)
        np.copyto(cur, h, where=take)
        np.copyto(self.cls[sl], cls, where=take)
        take3 = take[..., None]
        np.copyto(self.top[sl], np.asarray(top_rgb, np.uint8), where=take3)
        np.copyto(self.wall[sl], np.asarray(wall_rgb, np.uint8), where=take3)


def windows_mask(z: np.ndarray, s: np.ndarray, floor_h: float = 3.2, bay: float = 2.6) -> np.ndarray:
    """Facade pattern: True where a wall point at height z, along-wall coordinate s, is a window pane."""
    fz = np.mod(z, floor_h) / floor_h
    fs = np.mod(s, bay) / bay
    return (fz > 0.35) & (fz < 0.8) & (fs > 0.2) & (fs < 0.75) & (z > 2.5)
