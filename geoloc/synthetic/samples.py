"""One sample = one place: build its world, pick the conditions of each view, render.

Every random draw comes from a generator seeded by (seed, split, index) alone, so a sample's pixels do not depend
on the number of workers or on which samples were generated before it.
"""
from __future__ import annotations

import cv2
import numpy as np

from . import nuisance
from . import traffic as T
from .aerial import render_aerial
from .appearance import Conditions, base_conditions, finish, noise_patch, other_time
from .world_config import SynthConfig
from .light import Lighting
from .panorama import CVUSA_HORIZON, SPHERE_HORIZON, panorama_rays
from .perspective import Pose, jitter_pose, lane_pose, pinhole_rays
from .places import Place, build_place
from .sky import Sky
from .street import FOG_DIST_M, render_street
from .styles import choose_style

SPLITS = {"train": 0, "val": 1}


def sample_rngs(seed: int, split: str, index: int, n: int = 8) -> list[np.random.Generator]:
    ss = np.random.SeedSequence([int(seed), SPLITS[split], int(index)])
    return [np.random.default_rng(s) for s in ss.spawn(n)]


def make_place(cfg: SynthConfig, rng: np.random.Generator, style_mix: dict | None = None,
               cells: int | None = None) -> Place:
    """A textured place world of `cells` (default: cfg.world_cells()) cells a side; cfg.style 'mix' draws the
    style from style_mix (default styles.DEFAULT_MIX)."""
    style = choose_style(rng, style_mix) if cfg.style == "mix" else cfg.style
    n = cfg.world_cells()[1] if cells is None else cells
    place = build_place(rng, style, n * cfg.cell_m, cfg.cell_m)
    _texture(place.world, rng)
    return place


def _texture(world, rng) -> None:
    """Per-cell brightness noise so large surfaces are not flat colour (+-5 levels on tops, +-2 on walls)."""
    noise = noise_patch(rng, world.height.shape)
    for arr, amp in ((world.top, 5.0), (world.wall, 2.0)):
        d = (noise * np.float32(amp)).astype(np.int16)
        cv2.add(arr, cv2.merge([d, d, d]), dst=arr, dtype=cv2.CV_8U)  # integer sum saturated to 0..255


def street_traffic(rng, place: Place, extent, aerial_agents, change: float, keep, radius, density):
    """The street view's traffic: each aerial agent stays with prob 1-change, fresh agents come with prob change."""
    kept = [a for a in aerial_agents if rng.random() >= change]
    fresh = T.sample_traffic(rng, place.roads, place.style, extent, keep, radius, density)
    return kept + [a for a in fresh if rng.random() < change]


def render_pair(cfg: SynthConfig, seed: int, split: str, index: int, sphere: bool) -> dict:
    """Aerial tile + street panorama of one place (cvusa: horizon band; cvact: full sphere).

    -> {'aerial': S x S x 3 uint8 RGB, 'pano': H x W x 3 uint8 RGB, 'pano_labels': H x W uint8 (0..9),
        'aerial_labels': S x S uint8, 'aerial_conditions', 'street_conditions', 'style'}.
    """
    r_world, r_cond, r_traffic, r_noise, r_sky, _, r_view, _ = sample_rngs(seed, split, index)
    gap = cfg.gap()
    place = make_place(cfg, r_world)
    extent = place.world.extent
    cond_a = base_conditions(r_cond, gap)
    cond_s = other_time(r_cond, gap, cond_a)
    agents_a = T.sample_traffic(r_traffic, place.roads, place.style, extent, [(0, 0)], 5.0, cfg.traffic)
    agents_s = street_traffic(r_traffic, place, extent, agents_a, gap.resolved()["traffic_change"],
                              [(0, 0)], 5.0, cfg.traffic)
    # each view's own nuisances (nuisance.py), from a stream nothing else draws from; None: no such nuisances
    view_a, view_s = ((None, None) if cfg.view_nuisance is None else
                      (nuisance.draw(r_view, cfg.view_nuisance), nuisance.draw(r_view, cfg.view_nuisance)))

    world_a = T.stamp(place.world, T.near(agents_a, cfg.tile_m / 2 + 20))
    tile_m = cfg.tile_m if view_a is None else nuisance.scaled_tile_m(cfg.tile_m, cfg.cell_m, view_a.tile_scale,
                                                                      world_a.n)
    rgb_a, cls_a = render_aerial(world_a, Lighting(world_a, cond_a.sun), tile_m, cfg.aerial_size,
                                 cond_a.season, None if view_a is None else view_a.class_gains)
    world_s = T.stamp(place.world, agents_s)
    h, w = (cfg.sphere_height, cfg.sphere_width) if sphere else (cfg.pano_height, cfg.pano_width)
    horizon = SPHERE_HORIZON if sphere else CVUSA_HORIZON
    height, street_extra = cfg.camera_height, {}
    if view_s is not None:
        horizon = nuisance.horizon_with_pitch(horizon, view_s.pitch_deg, h, w)
        height *= view_s.height_factor
        street_extra = dict(fog_dist=FOG_DIST_M * view_s.fog_factor, class_gains=view_s.class_gains)
    az, tan_el = panorama_rays(h, w, horizon)
    rgb_s, cls_s, _ = render_street(world_s, Lighting(world_s, cond_s.sun), Sky(r_sky, cond_s.sun),
                                    (0.0, 0.0, height), az, tan_el, cond_s.season, **street_extra)
    if view_a is not None:
        rgb_a, rgb_s = nuisance.respond(rgb_a, view_a, aerial=True), nuisance.respond(rgb_s, view_s, aerial=False)
    return dict(aerial=finish(rgb_a, cond_a, r_noise), pano=finish(rgb_s, cond_s, r_noise), pano_labels=cls_s,
                aerial_labels=cls_a,
                aerial_conditions=cond_a, street_conditions=cond_s, style=place.style)


def render_view(cfg: SynthConfig, place: Place, pose: Pose, cond: Conditions, agents, sky_rng_seed: int,
                noise_seed: int) -> dict:
    """The same pinhole pose twice, with and without the agents, under identical light, sky and sensor noise."""
    az, tan_el = pinhole_rays(cfg.view_size, cfg.fov_deg, pose.yaw)
    cam = (pose.x, pose.y, cfg.camera_height)
    out = {}
    for name, world in (("static", place.world), ("dynamic", T.stamp(place.world, agents))):
        sky = Sky(np.random.default_rng(sky_rng_seed), cond.sun)
        rgb, cls, _ = render_street(world, Lighting(world, cond.sun), sky, cam, az, tan_el, cond.season)
        out[f"rgb_{name}"] = finish(rgb, cond, np.random.default_rng(noise_seed))
        out[f"label_{name}"] = cls
    out["mask_dynamic"] = np.where(out["label_dynamic"] >= T.VEHICLE, 255, 0).astype(np.uint8)
    return out


def render_place_views(cfg: SynthConfig, seed: int, split: str, index: int) -> list[dict]:
    """A reference view and a query view (jittered pose, other time, other traffic) of one place."""
    r_world, r_cond, r_traffic, r_noise, r_sky, r_pose, *_ = sample_rngs(seed, split, index)
    gap = cfg.gap()
    place = make_place(cfg, r_world)
    extent = place.world.extent
    ref_pose = lane_pose(place.roads, r_pose)
    query_pose = jitter_pose(ref_pose, r_pose, cfg.jitter_m, cfg.jitter_yaw)
    cond_ref = base_conditions(r_cond, gap)
    cond_q = other_time(r_cond, gap, cond_ref)
    keep = [(ref_pose.x, ref_pose.y), (query_pose.x, query_pose.y)]
    views = []
    for role, pose, cond in (("reference", ref_pose, cond_ref), ("query", query_pose, cond_q)):
        # Street scenes for the dynamic-scene method are busier than the cross-view places: 3x the traffic.
        agents = T.sample_traffic(r_traffic, place.roads, place.style, extent, keep, 5.0, 3.0 * cfg.traffic)
        seeds = r_noise.integers(2**31, size=2)
        v = render_view(cfg, place, pose, cond, agents, int(seeds[0]), int(seeds[1]))
        v.update(role=role, pose=pose, conditions=cond, style=place.style)
        views.append(v)
    return views
