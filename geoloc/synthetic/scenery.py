"""Small things the place builders scatter: trees, hedges, fences, poles and signs, crop fields."""
from __future__ import annotations

import cv2
import numpy as np

from . import styles as S
from .appearance import noise_patch
from .classes import FENCES, NONE, OTHERS, VEGETATION
from .roads import Road, rect
from .world import World


def tree(world: World, rng, x: float, y: float, scale: float = 1.0) -> None:
    if not world.contains(x, y, 5.0):
        return
    u = rng.random(3).tolist()  # one draw: thousands of trees per place
    r = scale * (1.8 + 2.2 * u[0])
    world.stamp_dome(x, y, r, h_base=(1.5 + 2.5 * u[1]) * scale, h_crown=r * (0.9 + 0.7 * u[2]),
                     cls=VEGETATION, rgb=S.pick(rng, S.TREE, 10))


def forest(world: World, rng, c, bearing: float, length: float, width: float, spacing: float) -> None:
    """A wood filling a rotated rectangle: one continuous canopy whose smooth bumps, about `spacing` apart, read
    as crowns from above and as a ragged tree line from the road (one vectorised stamp, not one per tree)."""
    pts = world._pts(rect(c, bearing, length, width))
    lo = np.maximum(pts.min(0) >> 4, 0)
    hi = np.minimum((pts.max(0) >> 4) + 2, world.n)
    if np.any(hi <= lo):
        return
    mask = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
    cv2.fillPoly(mask, [pts - (lo << 4)], 1, cv2.LINE_8, 4)
    inside = mask.astype(bool)
    if not inside.any():
        return
    sigma = max(0.6, 0.3 * spacing / world.cell)
    bumps = cv2.GaussianBlur(noise_patch(rng, mask.shape), (0, 0), sigma)
    bumps /= bumps.std() + 1e-6
    # Crowns lean out at the edge: the canopy rises over the first ~5 m, so the road sees lit crowns, not a wall.
    edge = cv2.distanceTransform(mask, cv2.DIST_L2, 3) * np.float32(world.cell / 5.0)
    canopy = ((rng.uniform(7.0, 11.0) + 1.6 * bumps) * np.minimum(0.45 + edge, 1.0)).astype(np.float32)
    base = np.asarray(S.pick(rng, S.TREE, 8), np.float32)
    top = np.clip(base * (1.0 + 0.12 * bumps[..., None]), 0, 255).astype(np.uint8)
    sl = (slice(lo[1], hi[1]), slice(lo[0], hi[0]))
    world._write(sl, inside, canopy, VEGETATION, top, tuple(int(min(255, v * 1.1)) for v in base))


def _axes(bearing: float):
    a = np.deg2rad(bearing)
    return np.array([np.sin(a), np.cos(a)]), np.array([np.cos(a), -np.sin(a)])


def tree_line(world: World, rng, a, b, spacing: float = 6.0) -> None:
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(2, int(np.linalg.norm(b - a) / spacing))
    for s in np.linspace(0, 1, n):
        if rng.random() < 0.85:
            p = a + s * (b - a) + rng.normal(0, 0.8, 2)
            tree(world, rng, p[0], p[1], rng.uniform(0.8, 1.2))


def hedge(world: World, rng, pts) -> None:
    world.draw_polyline(np.asarray(pts, float), max(0.8, world.cell), VEGETATION, S.pick(rng, S.TREE, 8),
                        rng.uniform(0.8, 1.6))


def fence(world: World, rng, pts, rgb=None) -> None:
    world.draw_polyline(np.asarray(pts, float), max(0.15, world.cell), FENCES,
                        rgb or S.pick(rng, S.FENCE, 8), rng.uniform(1.0, 1.8))


def pole(world: World, rng, x: float, y: float, height: float, rgb=None) -> None:
    c = rgb or S.pick(rng, S.METAL, 6)
    world.stamp_column(x, y, height, OTHERS, c, c)


def kerb_furniture(world: World, rng, road: Road, spacing: float, sign_p: float = 0.25) -> None:
    """Street lights / power poles along one or both kerbs, with the odd traffic sign."""
    p, t, n = road.frames()
    off = road.half_width + (road.sidewalk_w - 0.6 if road.sidewalk_w > 0 else 1.5)
    sides = (-1, 1) if road.sidewalk_w > 0 else (int(rng.choice([-1, 1])),)
    step = max(1, int(spacing))
    start = int(rng.integers(step))
    for side in sides:
        for i in range(start, len(p), step):
            q = p[i] + side * off * n[i]
            if not world.contains(q[0], q[1], 1.0) or q[0] ** 2 + q[1] ** 2 < 36.0:
                continue  # outside, or so close to the camera that it would fill the view
            pole(world, rng, q[0], q[1], rng.uniform(6.0, 9.0))
            if rng.random() < sign_p:
                j = min(len(p) - 1, i + step // 2)
                s = p[j] + side * off * n[j]
                if s[0] ** 2 + s[1] ** 2 < 36.0:
                    continue
                world.stamp_box(s[0], s[1], 0.8, max(0.3, world.cell * 1.01), 0.0, rng.uniform(2.2, 3.0), 0.0,
                                OTHERS, S.pick(rng, [(200, 30, 30), (30, 60, 160), (220, 220, 220)], 10),
                                S.pick(rng, S.METAL, 6))


def field(world: World, rng, c, bearing: float, length: float, width: float, rows_along: bool) -> None:
    """A crop field (Vegetation, with crop-row stripes) or bare soil (class None: it is not vegetation),
    filling a rotated rectangle."""
    poly = rect(c, bearing, length, width)
    if rng.random() < 0.3:
        world.fill_polygon(poly, NONE, S.pick(rng, S.SOIL, 8), 0.0)
        return
    base = S.pick(rng, S.CROPS, 10)
    world.fill_polygon(poly, VEGETATION, base, 0.0)
    dark = tuple(int(v * 0.82) for v in base)
    e1, e2 = _axes(bearing)
    if not rows_along:
        e1, e2, length, width = e2, e1, width, length
    c = np.asarray(c, float)
    spacing = rng.uniform(2.0, 4.0)
    mid = c + np.arange(-width / 2 + spacing / 2, width / 2 - 0.5, spacing)[:, None] * e2
    half = (length / 2 - 0.5) * e1
    rows = np.stack([mid - half, mid + half], 1)  # R x 2 x 2: one segment per crop row
    world.draw_polylines(rows, max(0.6, world.cell), VEGETATION, dark)
