"""Dynamic objects: cars on road lanes, pedestrians on sidewalks.

Traffic is drawn separately from the static world and stamped into a copy of it, so the same place can be rendered
with and without it, or with other traffic, under identical light. Shadows come for free from the height field.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import styles as S
from .classes import PEDESTRIAN, VEHICLE
from .world import World

# cars / pedestrians per 100 m of road, before the per-view density draw
DENSITY = {"urban": (4.5, 5.0), "suburban": (2.5, 1.2), "rural": (1.2, 0.15)}


@dataclass(frozen=True)
class Agent:
    kind: int  # VEHICLE or PEDESTRIAN
    x: float
    y: float
    bearing: float
    rgb: tuple
    size: float  # length scale


def sample_traffic(rng: np.random.Generator, roads, style: str, extent: float, keep_clear, clear_radius: float,
                   density: float = 1.0) -> list[Agent]:
    """Cars on lane centres (and parked at the kerb), pedestrians on sidewalks, none within clear_radius of any
    point in keep_clear (the cameras)."""
    cars_per_100, peds_per_100 = DENSITY[style]
    keep = np.asarray(keep_clear, float).reshape(-1, 2)
    agents = []
    for r in roads:
        p, t, n = r.frames()
        idx = np.flatnonzero(np.all(np.abs(p) < extent / 2 - 3, axis=1))
        if len(idx) == 0:
            continue
        for kind, rate in ((VEHICLE, cars_per_100), (PEDESTRIAN, peds_per_100)):
            if kind == PEDESTRIAN and r.sidewalk_w <= 0 and rng.random() > 0.3:
                continue
            count = min(int(rng.poisson(rate * density * len(idx) / 100.0)), len(idx))
            if count == 0:
                continue
            i = rng.choice(idx, size=count, replace=False)
            u = rng.random((count, 4))
            if kind == VEHICLE:
                off = (np.floor(u[:, 0] * r.lanes) + 0.5 - r.lanes / 2) * r.lane_w
                parked = u[:, 1] < 0.25  # against the kerb
                off = np.where(parked, np.sign(off) * (r.half_width - 1.1), off)
                heading = np.where((off < 0)[:, None], t[i], -t[i])  # drive on the right
            else:
                walk = r.sidewalk_w if r.sidewalk_w > 0 else 1.5
                side = np.where(u[:, 0] < 0.5, -1.0, 1.0)
                off = side * (r.half_width + 0.4 + u[:, 1] * max(0.1, walk - 0.8))
                heading = t[i] * np.where(u[:, 2] < 0.5, -1.0, 1.0)[:, None]
            q = p[i] + off[:, None] * n[i]
            ok = np.ones(count, bool)
            if len(keep):
                ok = np.min(np.linalg.norm(q[:, None] - keep[None], axis=2), axis=1) >= clear_radius
            bearing = np.rad2deg(np.arctan2(heading[:, 0], heading[:, 1]))
            palette = S.CAR if kind == VEHICLE else S.CLOTHES
            for j in np.flatnonzero(ok):
                agents.append(Agent(kind, float(q[j, 0]), float(q[j, 1]), float(bearing[j]), S.pick(rng, palette, 12),
                                    float(0.9 + 0.22 * u[j, 3])))
    return agents


def near(agents: list[Agent], half: float) -> list[Agent]:
    """The agents inside the square |x|, |y| < half (an aerial tile only needs its own, plus shadow casters)."""
    return [a for a in agents if abs(a.x) < half and abs(a.y) < half]


def stamp(world: World, agents: list[Agent]) -> World:
    """A copy of world with the agents in it (class 8 Vehicle / 9 Pedestrian)."""
    out = world.copy()
    out.base = world.static
    glass = (40, 48, 56)
    for a in agents:
        if a.kind == VEHICLE:
            out.stamp_vehicle(a.x, a.y, 4.4 * a.size, 1.85 * a.size, a.bearing, VEHICLE, a.rgb, glass)
        elif out.cell >= 0.4:  # a pedestrian fits in one cell
            out.stamp_column(a.x, a.y, 1.7 * a.size, PEDESTRIAN, (60, 44, 36), a.rgb)
        else:
            s = 0.45
            out.stamp_box(a.x, a.y, s, s * 0.8, a.bearing, 1.7 * a.size, 0.0, PEDESTRIAN, (60, 44, 36), a.rgb)
    return out
