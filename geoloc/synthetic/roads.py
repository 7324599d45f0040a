"""Roads: centre-line polylines with lanes, markings, sidewalks and crossings.

Every place has a road through the origin (the camera stands on it). Other code reads the `Road` list to put
cars on lanes, pedestrians on sidewalks and poles along the kerb.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import styles as S
from .classes import ROAD, ROADLINES, SIDEWALK
from .world import World


@dataclass
class Road:
    pts: np.ndarray  # K x 2 metres (x east, y north), resampled every ~1 m
    lanes: int
    lane_w: float
    sidewalk_w: float  # 0: none (a rural road has a soil/gravel shoulder instead)

    @property
    def half_width(self) -> float:
        return self.lanes * self.lane_w / 2

    def frames(self):
        """Per point: position, unit tangent, unit left normal (all K x 2). Kept while `pts` is the same array:
        a place asks for them about ten times per road."""
        kept = self.__dict__.get("_frames")
        if kept is None or kept[0] is not self.pts:
            d = np.gradient(self.pts, axis=0)
            t = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
            kept = self._frames = (self.pts, t, np.stack([-t[:, 1], t[:, 0]], 1))
        return kept


def bearing_vec(bearing_deg: float) -> np.ndarray:
    a = np.deg2rad(bearing_deg)
    return np.array([np.sin(a), np.cos(a)])


_SIGN_A = np.array([[-1.0], [1.0], [1.0], [-1.0]])  # the corners' sides along and across
_SIGN_B = np.array([[-1.0], [-1.0], [1.0], [1.0]])


def rect(c, bearing: float, length: float, width: float) -> np.ndarray:
    """Corners (4 x 2) of a rectangle centred at c with its long side along the bearing."""
    e1, e2 = bearing_vec(bearing), bearing_vec(bearing + 90)
    c = np.asarray(c, float)
    return c + _SIGN_A * length / 2 * e1 + _SIGN_B * width / 2 * e2


def straight(origin, bearing_deg: float, half_len: float) -> np.ndarray:
    e = bearing_vec(bearing_deg)
    s = np.arange(-half_len, half_len + 1e-6, 1.0)
    return np.asarray(origin, np.float64)[None] + s[:, None] * e[None]


def wavy(bearing_deg: float, half_len: float, amp: float, wavelength: float, phase: float) -> np.ndarray:
    """A gently curving road that passes exactly through the origin."""
    e1, e2 = bearing_vec(bearing_deg), bearing_vec(bearing_deg + 90)
    s = np.arange(-half_len, half_len + 1e-6, 1.0)
    off = amp * (np.sin(2 * np.pi * s / wavelength + phase) - np.sin(phase))
    return s[:, None] * e1[None] + off[:, None] * e2[None]


def visible(world: World, pts: np.ndarray, margin: float = 12.0, stride: int = 4) -> np.ndarray:
    """The part of a 1 m polyline near the world, every `stride`-th point: thick cv2 lines draw a round joint
    at every vertex, so fewer vertices draw much faster."""
    inside = np.flatnonzero(np.abs(pts).max(axis=1) < world.extent / 2 + margin)
    if len(inside) == 0:
        return pts[:0]
    sel = pts[inside[0] : inside[-1] + 1]
    chord = sel[-1] - sel[0]
    off = np.abs((sel[:, 0] - sel[0, 0]) * chord[1] - (sel[:, 1] - sel[0, 1]) * chord[0])
    if off.max() <= 0.05 * max(np.hypot(*chord), 1e-9):  # straight: the two ends are enough
        return sel[[0, -1]]
    return np.concatenate([sel[::stride], sel[-1:]])


def draw_roads(world: World, roads: list[Road], rng: np.random.Generator, crossings: bool) -> None:
    """Sidewalks first, then all asphalt, then markings, so intersections stay clean."""
    walk = S.pick(rng, S.CONCRETE, 6)
    asphalt = S.pick(rng, S.ASPHALT, 5)
    yellow_centre = rng.random() < 0.4
    for r in roads:
        if r.sidewalk_w > 0:
            world.draw_polyline(visible(world, r.pts), 2 * (r.half_width + r.sidewalk_w), SIDEWALK, walk, 0.0)
    for r in roads:
        world.draw_polyline(visible(world, r.pts), 2 * r.half_width, ROAD, asphalt, 0.0)
    line_w = max(0.15, world.cell)
    for r in roads:
        p, t, n = r.frames()
        centre = S.MARKING_YELLOW if yellow_centre else S.MARKING_WHITE
        edge = r.half_width - 0.3
        world.draw_polylines([visible(world, p + side * edge * n) for side in (-1, 1)], line_w, ROADLINES,
                             S.MARKING_WHITE)
        dashed = r.lanes % 2 == 1 or r.lanes > 2
        for k in range(1, r.lanes):
            off = (k - r.lanes / 2) * r.lane_w
            q = p + off * n
            if dashed or off != 0:
                inside = np.abs(q).max(axis=1) < world.extent / 2 + 5
                dashes = [q[a : a + 4] for a in range(0, len(q) - 3, 9) if inside[a]]  # 3 m dash, 6 m gap
                world.draw_polylines(dashes, line_w, ROADLINES, S.MARKING_WHITE)
            else:
                world.draw_polyline(visible(world, q), line_w, ROADLINES, centre)
    if crossings:
        _crossings(world, roads, line_w)


def _crossings(world: World, roads: list[Road], line_w: float) -> None:
    """Zebra stripes a few metres before each intersection of two roads."""
    half = world.extent / 2
    frames = [r.frames() for r in roads]
    segs = []
    for i, a in enumerate(roads):
        for j in range(i + 1, len(roads)):
            b = roads[j]
            if abs(np.dot(a.pts[-1] - a.pts[0], b.pts[-1] - b.pts[0])) > 0.95 * np.linalg.norm(
                    a.pts[-1] - a.pts[0]) * np.linalg.norm(b.pts[-1] - b.pts[0]):
                continue  # parallel: they never meet
            ia, ib = closest_points(a.pts, b.pts)
            if np.linalg.norm(a.pts[ia] - b.pts[ib]) > 1.5 or np.abs(a.pts[ia]).max() > half + 10:
                continue
            for road, (p, t, n), idx, other in ((a, frames[i], ia, b), (b, frames[j], ib, a)):
                for sgn in (-1, 1):
                    c = p[idx] + sgn * (other.half_width + other.sidewalk_w + 1.5) * t[idx]
                    q = c[None] + np.arange(-road.half_width + 0.5, road.half_width - 0.3, 1.0)[:, None] * n[idx]
                    segs += list(np.stack([q - 1.2 * t[idx], q + 1.2 * t[idx]], 1))
    world.draw_polylines(segs, max(line_w, 0.5), ROADLINES, S.MARKING_WHITE)


def closest_points(a: np.ndarray, b: np.ndarray, stride: int = 8):
    """Indices of the closest pair of points of two polylines: coarse search, then a local refinement."""
    d = np.linalg.norm(a[::stride, None] - b[None, ::stride], axis=2)
    ia, ib = np.unravel_index(np.argmin(d), d.shape)
    a0, b0 = max(0, ia * stride - stride), max(0, ib * stride - stride)
    sa, sb = a[a0 : a0 + 2 * stride + 1], b[b0 : b0 + 2 * stride + 1]
    d = np.linalg.norm(sa[:, None] - sb[None], axis=2)
    ja, jb = np.unravel_index(np.argmin(d), d.shape)
    return a0 + ja, b0 + jb
