"""The u1652 layout's buildings: a landmark at the centre of a place, a satellite tile centred on it, and oblique
"drone" views from an orbit around it, looking at it (University-1652's drone views circle each building while
descending).

The street renderer marches whole image columns, each a vertical half-plane at one compass azimuth, so it cannot
tilt a camera. A tilted pinhole is made in two steps: render the band of azimuths and elevations the pinhole
covers as a cylindrical image (columns uniform in azimuth, rows uniform in elevation, 1.5x finer than the
pinhole's pixels), then resample it at each pinhole pixel's direction.
"""
from __future__ import annotations

import cv2
import numpy as np

from . import scenery as Z
from . import styles as S
from . import traffic as T
from .aerial import render_aerial
from .appearance import base_conditions, finish, other_time
from .classes import BUILDINGS, SIDEWALK
from .world_config import SynthConfig
from .light import Lighting
from .roads import bearing_vec, rect
from .samples import make_place, street_traffic
from .sky import Sky
from .street import render_street
from .world import World

_LAYOUT_CODE = 3  # keeps the u1652 layout's random streams apart from the other layouts'
ORBIT_RADIUS = 0.5  # of tile_m: the drone circles the building at half a tile
ORBIT_HEIGHTS = (0.55, 0.3)  # of tile_m: first and last view's altitude (a descending orbit)
CAMPUS_HEIGHT = 9.0  # metres
CAMPUS_STYLES = {"urban": 0.3, "suburban": 0.5, "rural": 0.2}  # style 'mix' for a building's surroundings


def building_rngs(seed: int, split_code: int, index: int, n: int = 8) -> list[np.random.Generator]:
    ss = np.random.SeedSequence([int(seed), _LAYOUT_CODE, int(split_code), int(index)])
    return [np.random.default_rng(s) for s in ss.spawn(n)]


def check_geometry(cfg: SynthConfig) -> None:
    """The orbit must lie inside the place's world."""
    if cfg.world_margin < 1.2:
        raise ValueError(f"the u1652 layout needs world_margin >= 1.2 (the drone orbits {ORBIT_RADIUS} tile from "
                         f"the building, inside the world), got {cfg.world_margin}")


def render_building(cfg: SynthConfig, views: int, seed: int, split_code: int, index: int) -> dict:
    """-> {'satellite': RGB uint8 aerial_size^2, 'satellite_quality': int, 'drone': [RGB uint8 view_size^2] * views,
    'drone_quality': int}."""
    r_world, r_cond, r_traffic, r_noise, r_sky, r_orbit, *_ = building_rngs(seed, split_code, index)
    gap = cfg.gap()
    place = make_place(cfg, r_world, style_mix=CAMPUS_STYLES)
    # A campus: the neighbours inside the orbit are at most CAMPUS_HEIGHT tall, so the views see the building.
    cap_heights(place.world, (ORBIT_RADIUS + 0.1) * cfg.tile_m, CAMPUS_HEIGHT)
    stamp_landmark(place.world, r_world, cfg.tile_m)
    extent = place.world.extent
    cond_a = base_conditions(r_cond, gap)
    cond_d = other_time(r_cond, gap, cond_a)  # one flight: every view of a building shares its time
    agents_a = T.sample_traffic(r_traffic, place.roads, place.style, extent, [], 5.0, cfg.traffic)
    agents_d = street_traffic(r_traffic, place, extent, agents_a, gap.resolved()["traffic_change"], [], 5.0,
                              cfg.traffic)
    world_a = T.stamp(place.world, agents_a)
    rgb_a, _ = render_aerial(world_a, Lighting(world_a, cond_a.sun), cfg.tile_m, cfg.aerial_size, cond_a.season)
    world_d = T.stamp(place.world, agents_d)
    light_d, sky = Lighting(world_d, cond_d.sun), Sky(r_sky, cond_d.sun)
    drone = []
    for x, y, z, yaw, pitch in orbit(r_orbit, views, cfg.tile_m):
        z = max(z, roof_height(place.world, x, y, 4.0) + 5.0)  # never inside a tower: fly over it
        rgb, _ = oblique_view(world_d, light_d, sky, (x, y, z), yaw, pitch, cfg.view_size, cfg.fov_deg,
                              cond_d.season)
        drone.append(finish(rgb, cond_d, r_noise))
    return {"satellite": finish(rgb_a, cond_a, r_noise), "satellite_quality": cond_a.jpeg_quality,
            "drone": drone, "drone_quality": cond_d.jpeg_quality}


def stamp_landmark(world: World, rng: np.random.Generator, tile_m: float) -> None:
    """Clear a plaza at the origin and put the building there: a main block, often a wing (an L or T plan) and
    sometimes a tower, sized to the tile."""
    theta = rng.uniform(0, 180)
    length = rng.uniform(0.16, 0.3) * tile_m
    width = rng.uniform(0.55, 0.9) * length
    world.fill_polygon(rect((0.0, 0.0), theta, length + 14, width + 14), SIDEWALK, S.pick(rng, S.CONCRETE, 8), 0.0)
    height = rng.uniform(10, 35)
    gable = rng.random() < 0.4
    roof = S.pick(rng, S.ROOF if gable else S.FLAT_ROOF, 10)
    facade = S.pick(rng, S.FACADE, 12)
    world.stamp_box(0.0, 0.0, length, width, theta, height, rng.uniform(3, 7) if gable else 0.0, BUILDINGS, roof,
                    facade, ridge_along=True)
    across, along = bearing_vec(theta + 90), bearing_vec(theta)
    if rng.random() < 0.6:
        w_len, w_wid = rng.uniform(0.5, 0.9) * width, rng.uniform(0.3, 0.5) * length
        c = rng.choice([-1, 1]) * (width / 2 + w_len / 2 - 1) * across + rng.uniform(-0.3, 0.3) * length * along
        world.stamp_box(c[0], c[1], w_len, w_wid, theta + 90, height * rng.uniform(0.5, 0.9), 0.0, BUILDINGS, roof,
                        facade)
    if rng.random() < 0.35:
        c = rng.choice([-1, 1]) * 0.35 * length * along + rng.choice([-1, 1]) * 0.3 * width * across
        side = rng.uniform(0.15, 0.25) * width
        world.stamp_box(c[0], c[1], side, side, theta, height * rng.uniform(1.4, 1.9), 0.0, BUILDINGS,
                        S.pick(rng, S.FLAT_ROOF, 10), facade)
    for corner in rect((0.0, 0.0), theta, length + 10, width + 10):
        if rng.random() < 0.5:
            Z.tree(world, rng, corner[0], corner[1])


def cap_heights(world: World, radius: float, cap: float) -> None:
    """Cut everything within radius metres of the origin down to cap metres (a flat roof at the cut)."""
    c = (np.arange(world.n) + 0.5) * world.cell - world.extent / 2
    inside = (c[None, :] ** 2 + c[:, None] ** 2) < radius * radius
    np.minimum(world.height, np.float32(cap), out=world.height, where=inside)


def orbit(rng: np.random.Generator, views: int, tile_m: float) -> list[tuple[float, float, float, float, float]]:
    """One descending circle around the origin -> [(x, y, z, yaw, pitch)] in metres and degrees, each view
    looking at the building's foot (yaw: compass heading, pitch: degrees below the horizon)."""
    start = rng.uniform(0, 360)
    radius = ORBIT_RADIUS * tile_m
    out = []
    for k in range(views):
        phi = start + 360.0 * k / views + rng.uniform(-3, 3)
        z = tile_m * np.interp(k / max(views - 1, 1), [0, 1], ORBIT_HEIGHTS)
        a = np.deg2rad(phi)
        out.append((float(radius * np.sin(a)), float(radius * np.cos(a)), float(z), float((phi + 180) % 360),
                    float(np.rad2deg(np.arctan2(z, radius)))))
    return out


def pinhole_directions(size: int, fov_deg: float, pitch: float):
    """A square pinhole (horizontal fov = vertical fov) pitched down by `pitch` degrees -> (azimuth relative to its
    heading, elevation), both size x size degrees, at the pixel centres."""
    f = (size / 2) / np.tan(np.deg2rad(fov_deg) / 2)
    c = (np.arange(size, dtype=np.float64) + 0.5) - size / 2
    u, v = c[None, :], c[:, None]
    p = np.deg2rad(pitch)
    # direction = f * forward + u * right - v * up, in (right, ahead, up) of the heading
    right, ahead, up = u + 0 * v, f * np.cos(p) - v * np.sin(p), -f * np.sin(p) - v * np.cos(p)
    return np.rad2deg(np.arctan2(right, ahead)), np.rad2deg(np.arctan2(up, np.hypot(right, ahead)))


def oblique_view(world: World, light: Lighting, sky: Sky, cam_xyz, yaw: float, pitch: float, size: int,
                 fov_deg: float, season: float):
    """A pitched pinhole at cam_xyz -> (rgb float size x size x 3 in [0, 1], class map size x size uint8)."""
    az_rel, el = pinhole_directions(size, fov_deg, pitch)
    step = np.rad2deg(np.arctan(2 * np.tan(np.deg2rad(fov_deg) / 2) / size)) / 1.5
    a0, e_top = az_rel.min() - step, el.max() + step
    cols = int(np.ceil((az_rel.max() + step - a0) / step))
    rows = int(np.ceil((e_top - (el.min() - step)) / step))
    az = (yaw + a0 + (np.arange(cols) + 0.5) * step) % 360.0
    tan_el = np.tan(np.deg2rad(e_top - (np.arange(rows) + 0.5) * step))[:, None]
    d_max = exit_distance(world, cam_xyz[0], cam_xyz[1], az) - 2 * world.cell
    rgb, cls, _ = render_street(world, light, sky, cam_xyz, az, tan_el, season, d_max=d_max)
    map_x = ((az_rel - a0) / step - 0.5).astype(np.float32)
    map_y = ((e_top - el) / step - 0.5).astype(np.float32)
    out = cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out, cv2.remap(cls, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)


def roof_height(world: World, x: float, y: float, radius: float) -> float:
    """The highest point of the (static) world within radius metres of (x, y), in each axis."""
    col, row = world.to_cell(x, y)
    r = int(np.ceil(radius / world.cell))
    c0, r0 = max(0, int(col) - r), max(0, int(row) - r)
    patch = world.height[r0 : int(row) + r + 1, c0 : int(col) + r + 1]
    return float(patch.max()) if patch.size else 0.0


def exit_distance(world: World, x: float, y: float, az_deg: np.ndarray) -> float:
    """The shortest horizontal distance from (x, y) along any of the azimuths to the edge of the world square."""
    a = np.deg2rad(np.asarray(az_deg, np.float64))
    half = world.extent / 2
    t = []
    for pos, u in ((x, np.sin(a)), (y, np.cos(a))):
        with np.errstate(divide="ignore"):
            t.append(np.where(u > 0, (half - pos) / u, np.where(u < 0, (-half - pos) / u, np.inf)))
    return float(np.min(np.minimum(*t)))
