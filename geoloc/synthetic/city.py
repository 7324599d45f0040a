"""The vigor layout's cities: one seeded world per city, cut into overlapping satellite tiles, and street
panoramas taken anywhere on its roads.

A city world spans the tile grid plus, around the outermost panorama positions, half a street-view world
(`tile_m * world_margin`, as the cvusa places). Its satellite tiles are crops of one orthophoto of the city (one sun,
season and set of cars, like a real mosaic). A panorama is rendered from a crop of the city world centred on it, so
it sees as far in every direction as a cvusa panorama does; it has its own time and traffic.
"""
from __future__ import annotations

import functools
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from geoloc.data.geo import latlon_to_offset, offset_to_latlon

from . import traffic as T
from .aerial import render_aerial_window
from .appearance import Conditions, base_conditions, finish, other_time
from .classes import ROAD, ROADLINES
from .world_config import SynthConfig
from .light import Lighting
from .panorama import SPHERE_HORIZON, panorama_rays
from .places import Place
from .samples import make_place, street_traffic
from .sky import Sky
from .street import render_street
from .tiles import TileGrid
from .world import World

# VIGOR's cities (its folder names) and a downtown point of each: the synthetic city's centre.
CITY_ORIGINS = {"Chicago": (41.8781, -87.6298), "NewYork": (40.7580, -73.9855),
                "SanFrancisco": (37.7749, -122.4194), "Seattle": (47.6062, -122.3321)}
CITY_NAMES = tuple(CITY_ORIGINS)
CITY_STYLES = {"urban": 0.6, "suburban": 0.4}  # style 'mix' for a city: VIGOR's panoramas are all downtown
_LAYOUT_CODE = 2  # keeps the vigor layout's random streams apart from the other layouts'


@dataclass
class City:
    index: int  # in CITY_NAMES
    name: str
    origin: tuple[float, float]  # (lat, lon) of the grid centre
    grid: TileGrid
    place: Place
    crop_cells: int  # side of a panorama's world
    aerial: Conditions
    aerial_agents: list


def city_rngs(seed: int, city: int, *key: int, n: int = 5) -> list[np.random.Generator]:
    """Independent streams for one city (no key) or one of its panoramas (key = split code, index)."""
    ss = np.random.SeedSequence([int(seed), _LAYOUT_CODE, int(city), *map(int, key)])
    return [np.random.default_rng(s) for s in ss.spawn(n)]


@functools.lru_cache(maxsize=2)  # a worker renders many panoramas of one city: build its world once
def build_city(cfg: SynthConfig, grid_n: int, seed: int, city: int) -> City:
    grid = TileGrid.fit(grid_n, cfg.tile_m, cfg.cell_m)
    crop = 2 * int(round(grid.tile_cells * cfg.world_margin / 2))
    side = crop + (grid_n - 1) * grid.tile_cells // 2  # panoramas within the tile centres, each with crop/2 around
    r_world, r_cond, r_traffic, *_ = city_rngs(seed, city)
    place = make_place(cfg, r_world, style_mix=CITY_STYLES, cells=side)
    aerial = base_conditions(r_cond, cfg.gap())
    agents = T.sample_traffic(r_traffic, place.roads, place.style, place.world.extent, [], 5.0, cfg.traffic)
    name = CITY_NAMES[city]
    return City(city, name, CITY_ORIGINS[name], grid, place, crop, aerial, agents)


def render_tiles(cfg: SynthConfig, city: City, seed: int) -> Iterator[tuple[int, int, np.ndarray]]:
    """Every satellite tile of the city, row by row from the north-west -> (ix, iy, RGB uint8 aerial_size^2)."""
    world = T.stamp(city.place.world, city.aerial_agents)
    light = Lighting(world, city.aerial.sun)
    r_noise = city_rngs(seed, city.index)[3]
    for iy in range(city.grid.n):
        for ix in range(city.grid.n):
            rows, cols = city.grid.cells(ix, iy, world.n)
            rgb, _ = render_aerial_window(world, light, rows, cols, cfg.aerial_size, city.aerial.season)
            yield ix, iy, finish(rgb, city.aerial, r_noise)


def standing_half_span(city: City) -> float:
    """Metres: a panorama stands where |east| and |north| are at most this, between the outermost tile centres
    (so four tiles hold it), less 0.1 m so that rounding it onto VIGOR's lat/lon grid keeps it there."""
    return city.grid.half_span_m - 0.1


def panorama_position(city: City, rng: np.random.Generator, tries: int = 400) -> tuple[float, float]:
    """(east, north) metres on a road (else on open ground) between the outermost tile centres, moved onto the
    6-decimal lat/lon grid of VIGOR's panorama names (at most 6 cm), so the name says exactly where it was taken."""
    world, half = city.place.world, standing_half_span(city)
    best = None
    for _ in range(tries):
        e, n = rng.uniform(-half, half, 2)
        idx, _ = world.cell_index(e, n)
        if world.height.flat[idx] < 0.3:
            if world.cls.flat[idx] in (ROAD, ROADLINES):
                best = (e, n)
                break
            best = best or (e, n)
    e, n = best if best is not None else (e, n)
    latlon = np.round(offset_to_latlon(city.origin, e, n), 6)
    e, n = latlon_to_offset(city.origin, latlon)
    return float(e), float(n)


def render_panorama(cfg: SynthConfig, city: City, rngs: list, east: float, north: float) -> dict:
    """The full-sphere panorama (sphere_height x sphere_width, north at the centre column) at (east, north), with
    rngs = (condition, traffic, sky, noise) streams. -> {'pano': RGB uint8, 'conditions': Conditions}."""
    r_cond, r_traffic, r_sky, r_noise = rngs
    gap = cfg.gap()
    cond = other_time(r_cond, gap, city.aerial)
    place = city.place
    agents = street_traffic(r_traffic, place, place.world.extent, city.aerial_agents,
                            gap.resolved()["traffic_change"], [(east, north)], 5.0, cfg.traffic)
    local, (ce, cn) = _crop(place.world, east, north, city.crop_cells)
    half = local.extent / 2 + 5.0
    moved = [replace(a, x=a.x - ce, y=a.y - cn) for a in agents if abs(a.x - ce) < half and abs(a.y - cn) < half]
    local = T.stamp(local, moved)
    az, tan_el = panorama_rays(cfg.sphere_height, cfg.sphere_width, SPHERE_HORIZON)
    rgb, _, _ = render_street(local, Lighting(local, cond.sun), Sky(r_sky, cond.sun),
                              (east - ce, north - cn, cfg.camera_height), az, tan_el, cond.season)
    return {"pano": finish(rgb, cond, r_noise), "conditions": cond}


def _crop(world: World, east: float, north: float, side: int) -> tuple[World, tuple[float, float]]:
    """The side x side cells centred on the cell corner nearest (east, north) -> (world, its centre in metres)."""
    col, row = world.to_cell(east, north)
    c, r = int(round(float(col))), int(round(float(row)))
    h = side // 2
    if min(r, c) < h or max(r, c) + h > world.n:
        raise ValueError(f"a {side}-cell crop at ({east:.1f}, {north:.1f}) m does not fit the {world.n}-cell city")
    sl = (slice(r - h, r + h), slice(c - h, c + h))
    crop = World(world.cell, world.height[sl].copy(), world.cls[sl].copy(), world.top[sl].copy(),
                 world.wall[sl].copy())
    half = world.extent / 2
    return crop, (c * world.cell - half, half - r * world.cell)
