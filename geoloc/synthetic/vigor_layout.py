"""The vigor layout: VIGOR's released tree, read back by geoloc.datasets.vigor.

    <City>/satellite/satellite_<lat>_<lon>.png     every tile of the city's grid (aerial_size, PNG)
    <City>/panorama/<panoid>,<lat>,<lon>,.jpg      full-sphere panoramas (sphere_width x sphere_height)
    splits/<City>/satellite_list.txt               the tiles, row by row from the north-west
    splits/<City>/same_area_balanced_train.txt     `train` panoramas of the city
    splits/<City>/same_area_balanced_test.txt      `val` panoramas of the city
    splits/<City>/pano_label_balanced.txt          all of them, train lines then test lines (cross-area)

A split line is VIGOR's 13 fields: the panorama, then the positive and three semi-positive tiles (tiles.py), each
with the tile centre minus the panorama position as (north, east) satellite pixels, rounded, written like "23.0".
Jobs: one per city for its tiles, one per panorama.
"""
from __future__ import annotations

import string
from pathlib import Path

from geoloc.data.geo import offset_to_latlon

from . import layouts as LY
from .city import CITY_NAMES, City, build_city, city_rngs, panorama_position, render_panorama, render_tiles
from .config import SynthConfig, VigorOptions

SPLIT_CODES = {"train": 1, "val": 2}
SPLIT_FILES = {"train": "same_area_balanced_train.txt", "val": "same_area_balanced_test.txt"}
CROSS_AREA_FILE = "pano_label_balanced.txt"
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
        city = build_city(cfg, opts.grid, seed, index)
        names = []
        for ix, iy, rgb in render_tiles(cfg, city, seed):
            names.append(satellite_name(city, ix, iy))
            LY.write_bytes(root / city.name / "satellite" / names[-1], LY.encode(rgb, ".png"), atomic=False)
        return {"kind": kind, "city": index, "names": names}
    c, k = index
    city = build_city(cfg, opts.grid, seed, c)
    r_pos, *rngs = city_rngs(seed, c, SPLIT_CODES[kind], k)
    east, north = panorama_position(city, r_pos)
    panoid = "".join(r_pos.choice(list(ID_CHARS), 22))
    lat, lon = offset_to_latlon(city.origin, east, north)
    name = f"{panoid},{lat:.6f},{lon:.6f},.jpg"
    out = render_panorama(cfg, city, rngs, east, north)
    LY.write_bytes(root / city.name / "panorama" / name,
                   LY.encode(out["pano"], ".jpg", out["conditions"].jpeg_quality), atomic=False)
    return {"kind": kind, "city": c, "line": split_line(city, name, east, north, cfg.aerial_size)}


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
    lat, lon = offset_to_latlon(city.origin, *city.grid.centre(ix, iy))
    return f"satellite_{float(lat)!r}_{float(lon)!r}.png"


def split_line(city: City, pano_name: str, east: float, north: float, tile_px: int) -> str:
    """VIGOR's 13 fields for a panorama at (east, north) metres."""
    metres_per_px = city.grid.tile_m / tile_px
    fields = [pano_name]
    for ix, iy in city.grid.tiles_holding(east, north):
        ce, cn = city.grid.centre(ix, iy)
        fields += [satellite_name(city, ix, iy), f"{round((cn - north) / metres_per_px):.1f}",
                   f"{round((ce - east) / metres_per_px):.1f}"]
    return " ".join(fields)
