"""A city's roads where panoramas stand, as a graph a vehicle drives: each road's centreline where it is road in
the world and inside the area (a `Stretch`), and the points where two of them cross.

`drive` is the vehicle. It starts at a random point of the city's street network, going a way that leads on (to a
crossing, or far enough for the whole drive), and follows the centreline. At a crossing it goes straight on or turns
onto the other road: one of the ways that lead on, drawn at random; when none does, the way with the most road
ahead, turning back there counted among them. Where its stretch ends (the area's edge, or something built on the
road) it turns back (a U-turn). A city of a few tiles can hold a single crossing, and then only U-turns keep a long
drive inside its tiles.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .classes import ROAD, ROADLINES
from .roads import Road, closest_points
from .world import World

_EPS = 1e-9


@dataclass
class Stretch:
    pts: np.ndarray  # K x 2 metres (east, north): a road's 1 m centreline points inside the area, K >= 2
    arc: np.ndarray  # (K,) metres along the stretch from pts[0]
    crossings: list = field(default_factory=list)  # (arc here, the other stretch's index, arc there), by arc

    @property
    def length(self) -> float:
        return float(self.arc[-1])

    def at(self, s: float) -> np.ndarray:
        """(2,) the point `s` metres along."""
        return np.array([np.interp(s, self.arc, self.pts[:, 0]), np.interp(s, self.arc, self.pts[:, 1])])

    def between(self, s0: float, s1: float) -> np.ndarray:
        """The centreline from s0 to s1 metres along (either way round), end points included -> M x 2."""
        inner = self.pts[(self.arc > min(s0, s1)) & (self.arc < max(s0, s1))]
        return np.vstack([self.at(s0), inner if s1 >= s0 else inner[::-1], self.at(s1)])

    def next_crossing(self, s: float, way: int):
        """The first crossing strictly ahead of `s` going `way` (+1 along, -1 back) -> (arc, other, arc there) or
        None."""
        ahead = [c for c in self.crossings if way * (c[0] - s) > _EPS]
        return (ahead[0] if way > 0 else ahead[-1]) if ahead else None

    def room(self, s: float, way: int) -> float:
        """Metres from `s` to the stretch's end going `way`."""
        return self.length - s if way > 0 else s


def road_graph(world: World, roads: list[Road], half: float) -> list[Stretch]:
    """The stretches of `roads` where |east|, |north| <= half and the centreline lies on road cells of `world` (each
    run of such 1 m points is one stretch), with their crossings: where two centrelines meet within 1.5 m (as zebra
    crossings are found, roads.py), at the exact intersection of their local tangents (exact for the straight roads
    of a city grid)."""
    stretches = []
    for road in roads:
        cell, _ = world.cell_index(road.pts[:, 0], road.pts[:, 1])
        usable = (np.abs(road.pts).max(axis=1) <= half) & np.isin(world.cls.flat[cell], (ROAD, ROADLINES))
        on = np.flatnonzero(usable)
        for run in np.split(on, np.flatnonzero(np.diff(on) > 1) + 1):
            if len(run) >= 2:
                pts = road.pts[run]
                arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
                stretches.append(Stretch(pts, arc))
    for i, a in enumerate(stretches):
        for j in range(i + 1, len(stretches)):
            crossing = _crossing(a, stretches[j])
            if crossing is not None:
                a.crossings.append((crossing[0], j, crossing[1]))
                stretches[j].crossings.append((crossing[1], i, crossing[0]))
    for s in stretches:
        s.crossings.sort()
    return stretches


def _crossing(a: Stretch, b: Stretch) -> tuple[float, float] | None:
    """(arc on a, arc on b) where the two centrelines cross inside both stretches, or None."""
    ia, ib = closest_points(a.pts, b.pts)
    if np.linalg.norm(a.pts[ia] - b.pts[ib]) > 1.5:
        return None
    ta, tb = _tangent(a.pts, ia), _tangent(b.pts, ib)
    if abs(ta[0] * tb[1] - ta[1] * tb[0]) < 0.2:  # within 12° of parallel: no single crossing point
        return None
    u, v = np.linalg.solve(np.stack([ta, -tb], 1), b.pts[ib] - a.pts[ia])
    sa, sb = a.arc[ia] + u, b.arc[ib] + v
    if not (0.0 <= sa <= a.length and 0.0 <= sb <= b.length):
        return None
    return float(sa), float(sb)


def _tangent(pts: np.ndarray, i: int) -> np.ndarray:
    d = pts[min(i + 1, len(pts) - 1)] - pts[max(i - 1, 0)]
    return d / np.linalg.norm(d)


def drive(stretches: list[Stretch], rng: np.random.Generator, length: float) -> np.ndarray:
    """The centreline a vehicle drives for `length` metres (module docstring) -> M x 2 metres, no repeated point.
    It starts at a point drawn by length on the largest network of crossing stretches (the city's streets, not a
    bit of road left between buildings, where it would only turn back and forth)."""
    if not stretches:
        raise ValueError("the city has no road inside the area where panoramas stand")
    network = max(_networks(stretches), key=lambda ks: sum(stretches[k].length for k in ks))
    weights = np.array([stretches[k].length for k in network])
    i = network[int(rng.choice(len(network), p=weights / weights.sum()))]
    s = rng.uniform(0.0, stretches[i].length)
    i, s, way = _choose(stretches, [(i, s, -1), (i, s, 1)], length, rng)
    parts, left = [], float(length)
    while True:
        here = stretches[i]
        stop = here.next_crossing(s, way)
        to = stop[0] if stop else (here.length if way > 0 else 0.0)
        if abs(to - s) >= left:
            parts.append(here.between(s, s + way * left))
            break
        parts.append(here.between(s, to))
        left, s = left - abs(to - s), to
        if stop is None:
            way = -way  # the stretch ends: turn back
            continue
        ways = [(i, s, way)] + [(stop[1], stop[2], w) for w in (1, -1)]
        ways = [w for w in ways if stretches[w[0]].room(w[1], w[2]) > _EPS]
        i, s, way = _choose(stretches, ways, left, rng, back=(i, s, -way))
    path = np.vstack(parts)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(path, axis=0), axis=1) > _EPS])
    return path[keep]


def _networks(stretches: list[Stretch]) -> list[list[int]]:
    """The stretches grouped into networks: those joined by crossings, directly or through others."""
    seen, networks = set(), []
    for first in range(len(stretches)):
        if first in seen:
            continue
        todo, network = [first], []
        seen.add(first)
        while todo:
            k = todo.pop()
            network.append(k)
            for _, other, _ in stretches[k].crossings:
                if other not in seen:
                    seen.add(other)
                    todo.append(other)
        networks.append(sorted(network))
    return networks


def _choose(stretches: list[Stretch], ways: list, left: float, rng: np.random.Generator, back=None) -> tuple:
    """One of `ways` (stretch, arc, +-1) that leads on, at random; when none does, the one with the most road ahead,
    turning `back` counted among them (so a dead end is met as seldom as may be)."""
    leading = [w for w in ways if _leads_on(stretches, w, left)]
    if leading:
        return leading[int(rng.integers(len(leading)))]
    return max(ways + ([back] if back else []), key=lambda w: stretches[w[0]].room(w[1], w[2]))


def _leads_on(stretches: list[Stretch], way: tuple, left: float) -> bool:
    """Whether going this way reaches another crossing, or has room for the `left` metres of the drive."""
    k, s, w = way
    return stretches[k].next_crossing(s, w) is not None or stretches[k].room(s, w) >= left
