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
        inside = np.all(np.abs(p) < extent / 2 - 3, axis=1)
        idx = np.flatnonzero(inside)
        if len(idx) == 0:
            continue
        for kind, rate in ((VEHICLE, cars_per_100), (PEDESTRIAN, peds_per_100)):
            if kind == PEDESTRIAN and r.sidewalk_w <= 0 and rng.random() > 0.3:
                continue
            count = rng.poisson(rate * density * len(idx) / 100.0)
            for i in rng.choice(idx, size=min(count, len(idx)), replace=False):
                if kind == VEHICLE:
                    lane = int(rng.integers(r.lanes))
                    off = (lane + 0.5 - r.lanes / 2) * r.lane_w
                    if rng.random() < 0.25:  # parked against the kerb
                        off = np.sign(off) * (r.half_width - 1.1)
                    heading = t[i] if off < 0 else -t[i]  # drive on the right
                else:
                    walk = r.sidewalk_w if r.sidewalk_w > 0 else 1.5
                    off = rng.choice([-1, 1]) * (r.half_width + rng.uniform(0.4, max(0.5, walk - 0.4)))
                    heading = t[i] * rng.choice([-1, 1])
                q = p[i] + off * n[i]
                if len(keep) and np.min(np.linalg.norm(keep - q, axis=1)) < clear_radius:
                    continue
                bearing = float(np.rad2deg(np.arctan2(heading[0], heading[1])))
                rgb = S.pick(rng, S.CAR if kind == VEHICLE else S.CLOTHES, 12)
                agents.append(Agent(kind, float(q[0]), float(q[1]), bearing, rgb, float(rng.uniform(0.9, 1.12))))
    return agents


def stamp(world: World, agents: list[Agent]) -> World:
    """A copy of world with the agents in it (class 8 Vehicle / 9 Pedestrian)."""
    out = world.copy()
    out.base = world.static
    glass = (40, 48, 56)
    for a in agents:
        if a.kind == VEHICLE:
            L, W = 4.4 * a.size, 1.85 * a.size
            out.stamp_box(a.x, a.y, L, W, a.bearing, 0.85, 0.0, VEHICLE, a.rgb, a.rgb)
            dx, dy = np.sin(np.deg2rad(a.bearing)) * -0.2 * L, np.cos(np.deg2rad(a.bearing)) * -0.2 * L
            out.stamp_box(a.x + dx, a.y + dy, 0.5 * L, 0.9 * W, a.bearing, 1.45, 0.0, VEHICLE, a.rgb, glass)
        else:
            s = max(0.45, out.cell * 1.01)
            out.stamp_box(a.x, a.y, s, s * 0.8, a.bearing, 1.7 * a.size, 0.0, PEDESTRIAN, (60, 44, 36), a.rgb)
    return out
