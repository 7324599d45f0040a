"""Sun light: surface normals from the height field, cast shadows by height-field marching, Lambert shading."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .world import World


@dataclass(frozen=True)
class Sun:
    azimuth: float  # compass bearing of the sun, degrees clockwise from north
    elevation: float  # degrees above the horizon
    ambient: float = 0.45
    direct: float = 0.75

    def vector(self) -> np.ndarray:
        """Unit vector towards the sun, (east, north, up)."""
        a, e = np.deg2rad(self.azimuth), np.deg2rad(self.elevation)
        return np.array([np.sin(a) * np.cos(e), np.cos(a) * np.cos(e), np.sin(e)], np.float32)


@dataclass
class Lighting:
    """Per-cell shading terms of one world under one sun (N x N float32 each)."""

    top_shade: np.ndarray  # ambient + direct * lit * max(0, n . sun) for the top surface
    wall_nx: np.ndarray  # horizontal outward wall normal (east, north); zero away from height steps
    wall_ny: np.ndarray
    sun: Sun


def light_world(world: World, sun: Sun, shadow_cell: float = 1.0) -> Lighting:
    h = world.height
    inv2c = np.float32(0.5 / world.cell)
    gx = np.zeros_like(h)  # d/deast
    gy = np.zeros_like(h)  # d/dnorth (rows grow southward)
    gx[:, 1:-1] = (h[:, 2:] - h[:, :-2]) * inv2c
    gy[1:-1, :] = (h[:-2, :] - h[2:, :]) * inv2c
    g2 = gx * gx + gy * gy
    steep = g2 > 4.0  # a wall edge, not a sloped roof: the top there is flat
    s = sun.vector()
    nx = np.where(steep, np.float32(0), -gx)
    ny = np.where(steep, np.float32(0), -gy)
    cos_top = (nx * s[0] + ny * s[1] + s[2]) / np.sqrt(nx * nx + ny * ny + 1.0)
    lit = lit_fraction(world, sun, shadow_cell)
    top = sun.ambient + sun.direct * lit * np.maximum(cos_top, 0.0)
    inv_g = np.where(g2 > 0.25, 1.0 / np.sqrt(g2 + 1e-12), 0.0).astype(np.float32)  # walls and steep slopes
    return Lighting(top.astype(np.float32), -gx * inv_g, -gy * inv_g, sun)


def lit_fraction(world: World, sun: Sun, shadow_cell: float = 1.0) -> np.ndarray:
    """1 where a cell's surface sees the sun, 0 in cast shadow, soft at the edges.

    Marches on a coarse max-pooled grid: for each coarse cell, the height below which a point is shadowed is
    max over steps t of H(p + t*sun) - t*tan(elevation). Comparing that with the fine height keeps it monotone:
    adding an object (a car) only ever darkens other cells.
    """
    f = max(1, int(round(shadow_cell / world.cell)))
    n = world.n // f * f
    h = world.height[:n, :n].reshape(n // f, f, n // f, f).max(axis=(1, 3))
    m = h.shape[0]
    cs = world.cell * f
    tan_e = np.tan(np.deg2rad(max(sun.elevation, 3.0)))
    s = sun.vector()
    step = np.array([s[0], -s[1]]) / max(abs(s[0]), abs(s[1]))  # (dcol, drow) per coarse step
    step_len = cs * np.hypot(*step)
    hmax = float(h.max())
    shadow_h = np.full((m, m), -1.0, np.float32)
    k = 1
    while hmax - k * step_len * tan_e > 0.05 and k < m:
        dc, dr = int(round(k * step[0])), int(round(k * step[1]))
        drop = k * step_len * tan_e
        src = h[max(0, dr):m + min(0, dr), max(0, dc):m + min(0, dc)]
        dst = shadow_h[max(0, -dr):m + min(0, -dr), max(0, -dc):m + min(0, -dc)]
        np.maximum(dst, src - drop, out=dst)
        k += 1
    full = cv2.resize(shadow_h, (n, n), interpolation=cv2.INTER_LINEAR)
    if n != world.n:
        full = np.pad(full, ((0, world.n - n), (0, world.n - n)), mode="edge")
    soft = 0.35  # metres of penumbra
    return np.clip((world.height - full) / soft + 0.5, 0.0, 1.0).astype(np.float32)
