"""The vigor layout: VIGOR's released tree, read back by geoloc.datasets.vigor.

    <City>/satellite/satellite_<lat>_<lon>.png     every tile of the city's grid (aerial_size, PNG)
    <City>/panorama/<panoid>,<lat>,<lon>,.jpg      full-sphere panoramas (sphere_width x sphere_height)
    splits/<City>/satellite_list.txt               the tiles, row by row from the north-west
    splits/<City>/same_area_balanced_train.txt     `train` panoramas of the city
    splits/<City>/same_area_balanced_test.txt      `val` panoramas of the city
    splits/<City>/pano_label_balanced.txt          all of them, train lines then test lines (cross-area)

    geoloc_offsets.json                            the same offsets unrounded (geoloc's own; see below)

A split line is VIGOR's 13 fields: the panorama, then the positive and three semi-positive tiles (tiles.py), each
with the tile centre minus the panorama position as (north, east) satellite pixels, rounded, written like "23.0".
`geoloc_offsets.json` holds them unrounded, {"offsets": {city: {panorama: {satellite: [north, east]}}}}, so a
metre-level target can be measured; the reader (geoloc.datasets.vigor) uses it when present. It is derived from the
split files alone (the position a panorama's name gives is where it was rendered: panorama_position), so a dataset
rendered before the file existed gets it on its next use, its images untouched (`derived`).
Jobs: one per city for its tiles, one per panorama.
"""
from __future__ import annotations

import string
from pathlib import Path

from geoloc.data.geo import latlon_to_offset, offset_to_latlon
from geoloc.data.tile_offsets import OFFSETS_FILE, offsets_text

from . import layouts as LY
from .city import (CITY_NAMES, CITY_ORIGINS, City, build_city, city_rngs, panorama_position, render_panorama,
                   render_tiles)
from .world_config import SynthConfig, VigorOptions
from .tiles import TileGrid

SPLIT_CODES = {"train": 1, "val": 2}
SPLIT_FILES = {"train": "same_area_balanced_train.txt", "val": "same_area_balanced_test.txt"}
CROSS_AREA_FILE = "pano_label_balanced.txt"
DERIVED = (OFFSETS_FILE,)
ID_CHARS = string.ascii_letters + string.digits + "-_"  # 22 of them make an id like VIGOR's panoids


def check(cfg: SynthConfig, opts: VigorOptions) -> None:
    """Nothing beyond the options' own checks: any grid fits its city world by construction."""


def jobs(opts: VigorOptions, train: int, val: int) -> list:
    """(kind, index, number): ('tiles', city, n) per city, then ('train' / 'val', (city, k), n) per panorama."""
    out = [("tiles", c, c + 1) for c in range(opts.cities)]
    for split, count in (("train", train), ("val", val)):
        for c in range(opts.cities):
            for k in range(count):
                out.append((split, (c, k), len(out) + 1))
    return out


def run(cfg: SynthConfig, opts: VigorOptions, seed: int, kind: str, index, number: int, root: Path) -> dict:
    """Render and write one job's files -> its record (what finish() needs)."""
    if kind == "tiles":
        names = write_tiles(cfg, build_city(cfg, opts.grid, seed, index), seed, root)
        return {"kind": kind, "city": index, "names": names}
    c, k = index
    line = write_panorama(cfg, build_city(cfg, opts.grid, seed, c), seed, kind, k, root)
    return {"kind": kind, "city": c, "line": line}


def write_tiles(cfg: SynthConfig, city: City, seed: int, root: Path) -> list[str]:
    """Render and write every satellite tile of `city` -> their file names, row by row from the north-west."""
    names = []
    for ix, iy, rgb in render_tiles(cfg, city, seed):
        names.append(satellite_name(city, ix, iy))
        LY.write_bytes(root / city.name / "satellite" / names[-1], LY.encode(rgb, ".png"), atomic=False)
    return names


def write_panorama(cfg: SynthConfig, city: City, seed: int, split: str, k: int, root: Path) -> str:
    """Render and write panorama k of the city's `split` ('train' / 'val') -> its split line. Where it stands and
    its name come from (seed, city, split, k) alone; its look also from the city's aerial conditions."""
    r_pos, *rngs = city_rngs(seed, city.index, SPLIT_CODES[split], k)
    east, north = panorama_position(city, r_pos)
    panoid = "".join(r_pos.choice(list(ID_CHARS), 22))
    lat, lon = offset_to_latlon(city.origin, east, north)
    name = f"{panoid},{lat:.6f},{lon:.6f},.jpg"
    LY.write_bytes(root / city.name / "panorama" / name, panorama_jpeg(cfg, city, rngs, east, north), atomic=False)
    return split_line(city, name, east, north, cfg.aerial_size)


def panorama_jpeg(cfg: SynthConfig, city: City, rngs: list, east: float, north: float) -> bytes:
    """The JPEG file of the panorama at (east, north) (render_panorama), at the quality its conditions drew: every
    street panorama of a vigor world, a split's or a route's (routes.py), is written through this."""
    out = render_panorama(cfg, city, rngs, east, north)
    return LY.encode(out["pano"], ".jpg", out["conditions"].jpeg_quality)


def finish(root: Path, opts: VigorOptions, jobs: list, records: dict) -> None:
    """The split files, from the jobs' records (records: job number -> record)."""
    for c in range(opts.cities):
        folder = root / "splits" / CITY_NAMES[c]
        mine = [records[n] for _, _, n in jobs if records[n]["city"] == c]
        names = next(r["names"] for r in mine if r["kind"] == "tiles")
        LY.write_bytes(folder / "satellite_list.txt", "".join(f"{s}\n" for s in names).encode())
        lines = {split: "".join(r["line"] + "\n" for r in mine if r["kind"] == split) for split in SPLIT_FILES}
        for split, file in SPLIT_FILES.items():
            LY.write_bytes(folder / file, lines[split].encode())
        LY.write_bytes(folder / CROSS_AREA_FILE, (lines["train"] + lines["val"]).encode())


def satellite_name(city: City, ix: int, iy: int) -> str:
    return _satellite_name(city.origin, city.grid, ix, iy)


def _satellite_name(origin, grid: TileGrid, ix: int, iy: int) -> str:
    lat, lon = offset_to_latlon(origin, *grid.centre(ix, iy))
    return f"satellite_{float(lat)!r}_{float(lon)!r}.png"


def split_line(city: City, pano_name: str, east: float, north: float, tile_px: int) -> str:
    """VIGOR's 13 fields for a panorama at (east, north) metres."""
    fields = [pano_name]
    for ix, iy in city.grid.tiles_holding(east, north):
        d_north, d_east = tile_offset_px(city.grid, ix, iy, east, north, tile_px)
        fields += [satellite_name(city, ix, iy), f"{round(d_north):.1f}", f"{round(d_east):.1f}"]
    return " ".join(fields)


def tile_offset_px(grid: TileGrid, ix: int, iy: int, east: float, north: float, tile_px: int) -> tuple[float, float]:
    """Tile (ix, iy)'s centre minus the point (east, north) metres, as (north, east) pixels of a tile_px tile."""
    metres_per_px = grid.tile_m / tile_px
    ce, cn = grid.centre(ix, iy)
    return (cn - north) / metres_per_px, (ce - east) / metres_per_px


def derived(root: Path, cfg: SynthConfig, opts: VigorOptions) -> None:
    """Write geoloc_offsets.json (geoloc/data/tile_offsets.py) from the split files (module docstring): every
    panorama of pano_label_balanced.txt, each
    tile of its line, the offset unrounded."""
    grid = TileGrid.fit(opts.grid, cfg.tile_m, cfg.cell_m)
    offsets = {}
    for c in range(opts.cities):
        name, origin = CITY_NAMES[c], CITY_ORIGINS[CITY_NAMES[c]]
        tiles = {_satellite_name(origin, grid, ix, iy): (ix, iy) for iy in range(grid.n) for ix in range(grid.n)}
        city = offsets[name] = {}
        for line in (root / "splits" / name / CROSS_AREA_FILE).read_text().splitlines():
            fields = line.split()
            lat, lon = (float(v) for v in fields[0].split(",")[-3:-1])
            east, north = (float(v) for v in latlon_to_offset(origin, (lat, lon)))
            city[fields[0]] = {sat: list(tile_offset_px(grid, *tiles[sat], east, north, cfg.aerial_size))
                               for sat in fields[1::3]}
    LY.write_bytes(root / OFFSETS_FILE, offsets_text(offsets).encode())
