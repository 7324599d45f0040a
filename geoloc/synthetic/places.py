"""Place builders: one seeded local world per place, in one of three terrain styles.

- urban: a rotated street grid, 2-4 lane roads with sidewalks and zebra crossings, blocks filled with tall
  flat-roofed buildings, street trees and lights;
- suburban: wider grid, lawns, gable-roofed houses set back from the road, driveways, hedges, fences, trees;
- rural: one long (often curving) road through a patchwork of fields, bare soil and woods, tree lines, power
  poles, the odd farm. Like CVUSA, many rural places look alike.
The camera's road always passes through the origin.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import scenery as Z
from . import styles as S
from .classes import BUILDINGS, NONE, SIDEWALK, VEGETATION
from .roads import Road, bearing_vec, draw_roads, rect, straight, visible, wavy
from .world import World


@dataclass
class Place:
    world: World
    roads: list
    style: str


def build_place(rng: np.random.Generator, style: str, extent: float, cell: float) -> Place:
    if style not in S.STYLES:
        raise ValueError(f"unknown terrain style {style!r}; expected one of {S.STYLES}")
    return {"urban": _urban, "suburban": _suburban, "rural": _rural}[style](rng, extent, cell)


def _grid(rng, extent, spacing_range, lanes_choices, lane_w, walk_range):
    """Roads of a rotated grid; one road of the first family passes through the origin."""
    theta = rng.uniform(0, 180)
    half = extent * 0.75
    roads, lines = [], {0: [], 1: []}
    for fam, bearing in ((0, theta), (1, theta + 90)):
        sp = rng.uniform(*spacing_range)
        off = 0.0 if fam == 0 else rng.uniform(0, sp)
        e2 = bearing_vec(bearing + 90)
        for k in range(-int(half / sp) - 1, int(half / sp) + 2):
            v = off + k * sp
            r = Road(straight(v * e2, bearing, half), int(rng.choice(lanes_choices)), lane_w,
                     rng.uniform(*walk_range))
            roads.insert(0, r) if (fam == 0 and k == 0) else roads.append(r)
            lines[fam].append((v, r))
    return theta, roads, lines


def _blocks(theta, lines):
    """Block rectangles between consecutive grid roads: (centre, len along theta, len across)."""
    e1, e2 = bearing_vec(theta), bearing_vec(theta + 90)
    a = sorted(lines[0], key=lambda t: t[0])  # offsets along e2
    b = sorted(lines[1], key=lambda t: t[0])  # offsets along e1
    for (v0, r0), (v1, r1) in zip(a, a[1:]):
        for (u0, q0), (u1, q1) in zip(b, b[1:]):
            lo_v, hi_v = v0 + r0.half_width + r0.sidewalk_w, v1 - r1.half_width - r1.sidewalk_w
            lo_u, hi_u = u0 + q0.half_width + q0.sidewalk_w, u1 - q1.half_width - q1.sidewalk_w
            if hi_v - lo_v > 4 and hi_u - lo_u > 4:
                c = (lo_u + hi_u) / 2 * e1 + (lo_v + hi_v) / 2 * e2
                yield c, hi_u - lo_u, hi_v - lo_v


def _lots(rng, c, lu, lv, theta, width_range, rows):
    """Split a block into `rows` x n lots: yields (lot centre, along, across, side) with side = which road."""
    e1, e2 = bearing_vec(theta), bearing_vec(theta + 90)
    depth = lv / rows
    for row in range(rows):
        v = -lv / 2 + depth * (row + 0.5)
        u = -lu / 2
        while u < lu / 2 - 3:
            w = min(rng.uniform(*width_range), lu / 2 - u)
            yield c + (u + w / 2) * e1 + v * e2, w, depth, (-1 if row == 0 else 1)
            u += w


def _in_world(p, extent, margin=0.0):
    return np.all(np.abs(p) < extent / 2 + margin)


def _urban(rng, extent, cell):
    w = World.empty(extent, cell, S.pick(rng, S.CONCRETE, 8), NONE)
    theta, roads, lines = _grid(rng, extent, (55, 95), (2, 2, 4, 4, 3), 3.3, (3.0, 5.0))
    draw_roads(w, roads, rng, crossings=True)
    for c, lu, lv in _blocks(theta, lines):
        if not _in_world(c, extent, 0.75 * max(lu, lv)):
            continue
        for lc, lw, ld, _ in _lots(rng, c, lu, lv, theta, (10, 26), 2 if lv > 26 else 1):
            if not w.contains(lc[0], lc[1], max(lw, ld)):
                continue
            if rng.random() < 0.1:  # a small park
                w.fill_polygon(rect(lc, theta, lw, ld), VEGETATION, S.pick(rng, S.GRASS, 8), 0.0)
                Z.tree(w, rng, *lc)
                continue
            set_back = rng.uniform(0, 1.5)
            w.stamp_box(lc[0], lc[1], lw - 0.6, ld - 2 * set_back, theta, rng.uniform(9, 45), 0.0, BUILDINGS,
                        S.pick(rng, S.FLAT_ROOF, 8), S.pick(rng, S.FACADE, 12))
    for r in roads:
        Z.kerb_furniture(w, rng, r, rng.uniform(22, 32))
        if rng.random() < 0.5:  # street trees
            p, t, n = r.frames()
            for i in range(int(rng.integers(8)), len(p), 18):
                for side in (-1, 1):
                    q = p[i] + side * (r.half_width + r.sidewalk_w * 0.6) * n[i]
                    if not w.contains(q[0], q[1], 5.0):
                        continue
                    Z.tree(w, rng, q[0], q[1], 0.7)
    return Place(w, roads, "urban")


def _suburban(rng, extent, cell):
    w = World.empty(extent, cell, S.pick(rng, S.GRASS, 8), VEGETATION)
    theta, roads, lines = _grid(rng, extent, (80, 130), (2,), 3.2, (1.5, 2.5))
    draw_roads(w, roads, rng, crossings=rng.random() < 0.5)
    drive = S.pick(rng, S.CONCRETE, 8)
    for c, lu, lv in _blocks(theta, lines):
        if not _in_world(c, extent, 0.75 * max(lu, lv)):
            continue
        fence_rgb = S.pick(rng, S.FENCE, 6)
        for lc, lw, ld, side in _lots(rng, c, lu, lv, theta, (18, 30), 2):
            if not w.contains(lc[0], lc[1], max(lw, ld)):
                continue
            e2 = bearing_vec(theta + 90)
            front = lc + side * (ld / 2) * e2  # the lot edge on the road
            hd, hw = rng.uniform(8, 13), min(lw - 5, rng.uniform(9, 15))
            hc = front - side * (rng.uniform(5, 9) + hd / 2) * e2
            w.fill_polygon(rect((front + hc) / 2 + rng.uniform(-1, 1) * hw / 3 * bearing_vec(theta), theta + 90,
                                np.linalg.norm(front - hc), 3.0), SIDEWALK, drive, 0.0)
            w.stamp_box(hc[0], hc[1], hw, hd, theta, rng.uniform(3.0, 6.0), rng.uniform(1.5, 3.5), BUILDINGS,
                        S.pick(rng, S.ROOF, 10), S.pick(rng, S.HOUSE_WALL, 10), ridge_along=rng.random() < 0.7)
            back = lc - side * (ld / 2 - 1) * e2
            corner = rect(lc, theta, lw, ld)
            edge = (corner[0], corner[3]) if rng.random() < 0.5 else (corner[1], corner[2])
            if rng.random() < 0.5:
                Z.fence(w, rng, edge, fence_rgb)
            elif rng.random() < 0.5:
                Z.hedge(w, rng, edge)
            for _ in range(int(rng.integers(0, 3))):
                q = back + rng.uniform(-lw / 2, lw / 2) * bearing_vec(theta) + side * rng.uniform(0, 6) * e2
                Z.tree(w, rng, q[0], q[1])
    for r in roads:
        Z.kerb_furniture(w, rng, r, rng.uniform(30, 45), sign_p=0.15)
    return Place(w, roads, "suburban")


def _rural(rng, extent, cell):
    w = World.empty(extent, cell, S.pick(rng, S.SOIL, 8), NONE)
    theta = rng.uniform(0, 180)
    half = extent * 0.75
    # Field patchwork on its own slightly rotated grid.
    phi = theta + rng.uniform(-20, 20)
    e1, e2 = bearing_vec(phi), bearing_vec(phi + 90)
    fu, fv = rng.uniform(40, 110), rng.uniform(40, 110)
    ou, ov = rng.uniform(0, fu), rng.uniform(0, fv)
    for i in range(-int(half / fu) - 1, int(half / fu) + 2):
        for j in range(-int(half / fv) - 1, int(half / fv) + 2):
            c = (ou + i * fu) * e1 + (ov + j * fv) * e2
            if not _in_world(c, extent, 80):
                continue
            poly = rect(c, phi, fu - 1, fv - 1)
            kind = rng.random()
            if kind < 0.18:
                w.fill_polygon(poly, VEGETATION, S.pick(rng, S.GRASS, 10), 0.0)
                Z.forest(w, rng, c, phi, fu - 1, fv - 1, rng.uniform(5.0, 7.0))
            elif kind < 0.3:
                w.fill_polygon(poly, VEGETATION, S.pick(rng, S.GRASS, 10), 0.0)
            else:
                Z.field(w, rng, c, phi, fu - 1, fv - 1, rng.random() < 0.5)
            if rng.random() < 0.35:
                Z.tree_line(w, rng, poly[0], poly[1])
    roads = [Road(wavy(theta, half, rng.uniform(0, 12), rng.uniform(150, 400), rng.uniform(0, 2 * np.pi)),
                  2, rng.uniform(2.8, 3.4), 0.0)]
    if rng.random() < 0.4:
        o = rng.uniform(-40, 40) * bearing_vec(theta)
        roads.append(Road(straight(o, theta + 90 + rng.uniform(-25, 25), half), 2, rng.uniform(2.6, 3.2), 0.0))
    gravel = S.pick(rng, S.SOIL, 8)
    for r in roads:  # soil/gravel shoulder: class None
        w.draw_polyline(visible(w, r.pts), 2 * r.half_width + 3.0, NONE, gravel, 0.0)
    draw_roads(w, roads, rng, crossings=False)
    if rng.random() < 0.35:  # a farm: house, barn, trees
        p, t, n = roads[0].frames()
        i = int(rng.integers(len(p) // 4, 3 * len(p) // 4))
        side = rng.choice([-1, 1])
        hc = p[i] + side * rng.uniform(18, 35) * n[i]
        ang = np.rad2deg(np.arctan2(t[i, 0], t[i, 1]))
        w.stamp_box(hc[0], hc[1], rng.uniform(9, 14), rng.uniform(7, 10), ang, rng.uniform(3, 5.5),
                    rng.uniform(2, 3.5), BUILDINGS, S.pick(rng, S.ROOF, 10), S.pick(rng, S.HOUSE_WALL, 10))
        bc = hc + side * rng.uniform(16, 25) * n[i] + rng.uniform(-10, 10) * t[i]
        w.stamp_box(bc[0], bc[1], rng.uniform(16, 26), rng.uniform(10, 14), ang + 90, rng.uniform(4, 6),
                    rng.uniform(3, 5), BUILDINGS, S.pick(rng, S.ROOF, 10), S.pick(rng, [(140, 50, 40)], 15))
        for _ in range(4):
            q = hc + rng.uniform(-15, 15, 2)
            Z.tree(w, rng, q[0], q[1])
    for r in roads:
        Z.kerb_furniture(w, rng, r, rng.uniform(35, 50), sign_p=0.1)
        if rng.random() < 0.3:
            p, t, n = r.frames()
            side = rng.choice([-1, 1])
            Z.fence(w, rng, p[::5] + side * (r.half_width + 2.5) * n[::5])
    return Place(w, roads, "rural")
