"""Street-level rendering shared by the panorama and the pinhole camera: march, shade, fog, sky."""
from __future__ import annotations

import numpy as np

from .appearance import apply_season
from .light import Lighting
from .raymarch import march, sample_distances
from .sky import Sky
from .world import World

FOG_DIST_M = 450.0  # the haze's e-folding distance: 1 - exp(-d / FOG_DIST_M) of a hit's colour is haze


def render_street(world: World, light: Lighting, sky: Sky, cam_xyz, az_deg: np.ndarray, tan_el: np.ndarray,
                  season: float, fog_dist: float = FOG_DIST_M, d_max: float | None = None,
                  class_gains: np.ndarray | None = None):
    """Rays given by az_deg (W,) and tan_el (H, W) or (H, 1) -> (rgb float H x W x 3 in [0,1], cls H x W,
    dist H x W horizontal metres, inf for sky). d_max: how far the rays are marched; by default the radius that
    stays inside the grid in every direction (a caller that knows its rays' directions may pass more). class_gains
    (classes x 3): each class's albedo times its RGB gain (nuisance.py); None leaves it."""
    if d_max is None:
        d_max = 0.5 * world.extent - np.hypot(cam_xyz[0], cam_xyz[1]) - 2 * world.cell  # stay inside the grid
    hits = march(world, light, cam_xyz, az_deg, tan_el, sample_distances(world.cell, max(d_max, 5.0)))
    albedo = apply_season(hits.albedo, hits.cls, season)
    if class_gains is not None:
        albedo *= class_gains[hits.cls]
    rgb = albedo * hits.shade[..., None]
    tan_full = np.broadcast_to(tan_el, hits.cls.shape)
    az_full = np.broadcast_to(np.asarray(az_deg)[None, :], hits.cls.shape)
    fog = -np.expm1(hits.dist * np.float32(-1.0 / fog_dist))  # 1 - exp(-d / fog_dist); 1 at infinity
    haze = sky.horizon * np.float32(0.95)
    rgb += (haze - rgb) * fog[..., None]
    sky_px = np.isinf(hits.dist) & (tan_full >= 0)
    if sky_px.any():
        rgb[sky_px] = sky.color(az_full[sky_px], tan_full[sky_px])
    return rgb.astype(np.float32), hits.cls, hits.dist
