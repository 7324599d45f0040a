"""Pinhole street camera for the dynamic-scene method, posed on a road lane and looking along it."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Pose:
    x: float  # metres east of the place centre
    y: float  # metres north
    yaw: float  # compass heading, degrees clockwise from north


def pinhole_rays(size: int, fov_deg: float, yaw: float):
    """Square image, horizontal = vertical FOV, no roll or pitch -> az_deg (W,), tan_el (H, W).

    Pixel (v, u) centre looks along u' = u + 0.5 - c, v' = v + 0.5 - c with focal f = (size/2)/tan(fov/2):
    azimuth yaw + atan(u'/f), and tan(elevation) = -v' / sqrt(f^2 + u'^2).
    """
    if not 1.0 <= fov_deg < 179.0:
        raise ValueError(f"fov_deg must be in [1, 179), got {fov_deg}")
    f = (size / 2) / np.tan(np.deg2rad(fov_deg) / 2)
    c = (np.arange(size, dtype=np.float64) + 0.5) - size / 2
    az = (yaw + np.rad2deg(np.arctan2(c, f))) % 360.0
    tan_el = -c[:, None] / np.sqrt(f * f + c[None, :] ** 2)
    return az, tan_el


def lane_pose(roads, rng: np.random.Generator) -> Pose:
    """On the right-hand lane of the road through the origin, facing along it (either direction)."""
    r = roads[0]
    p, t, n = r.frames()
    i = int(np.argmin(np.linalg.norm(p, axis=1)))
    sgn = 1.0 if rng.random() < 0.5 else -1.0
    heading = sgn * t[i]
    pos = p[i] - sgn * (r.lane_w / 2 if r.lanes > 1 else 0.0) * n[i]
    return Pose(float(pos[0]), float(pos[1]), float(np.rad2deg(np.arctan2(heading[0], heading[1])) % 360))


def jitter_pose(pose: Pose, rng: np.random.Generator, jitter_m: float, jitter_yaw: float) -> Pose:
    """Move along the heading by up to jitter_m, sideways by a third of that, turn by up to jitter_yaw."""
    a = np.deg2rad(pose.yaw)
    along, side = rng.uniform(-jitter_m, jitter_m), rng.uniform(-jitter_m, jitter_m) / 3
    x = pose.x + along * np.sin(a) + side * np.cos(a)
    y = pose.y + along * np.cos(a) - side * np.sin(a)
    return Pose(float(x), float(y), float((pose.yaw + rng.uniform(-jitter_yaw, jitter_yaw)) % 360))
