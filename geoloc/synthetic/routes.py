"""Routes through a synthetic vigor world: a vehicle drives a city's roads and takes a panorama every `spacing_m`
metres, with the odometry it measures between them, for sequence localisation (many frames, one trajectory, the
satellite tiles of the same world).

    ROOT/routes/routes.json                              seed, count, frames, spacing, noise, version, config
    ROOT/routes/<City>/route_NNNN/frame_000.jpg ...      north-aligned panoramas, as the vigor layout's
    ROOT/routes/<City>/route_NNNN/odometry.csv           frame,distance_m,heading_change_deg
    ROOT/routes/<City>/route_NNNN/truth.csv              frame,lat,lon,east_m,north_m,heading_deg

`count` routes per city, numbered from 0. Frames stand on a road's centreline, on road cells, between the outermost
tile centres (where panoramas stand), `spacing_m` apart along the road: at a crossing the route goes straight on or
turns onto the other road, and where the road leaves that area (or is built on) it turns back (road_graph.py).
Odometry row i is the motion from frame i-1 to frame i: the distance driven (metres along the road, so a step round a
corner is longer than the straight line between its frames) times N(1, distance_noise), and the change of travel
heading (degrees, clockwise positive, the true one in (-180, 180], a U-turn about +-180) plus N(0,
heading_noise_deg); row 0 is 0,0.0,0.0. truth.csv holds the exact positions and travel headings (degrees clockwise
from north). Numbers are written with repr, so they read back exactly.

Everything a route holds comes from (seed, city, route index) alone. A route is one drive: one time of day, sky and
JPEG quality for all its frames; each frame has its own traffic and sensor noise. routes.json is written last, so a
routes folder without it is unfinished.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import shutil
import sys
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from geoloc.data.geo import offset_to_latlon

from . import layouts as LY
from .city import CITY_NAMES, City, build_city, city_rngs, standing_half_span
from .generate import vigor_marker
from .road_graph import drive, road_graph
from .vigor_layout import panorama_jpeg
from .world_config import SynthConfig, VigorOptions

VERSION = "1.0"
ROUTES_DIR = "routes"
ROUTES_FILE = "routes.json"
ROUTE_CODE = 3  # a route's city_rngs key: apart from the panoramas' (vigor_layout.SPLIT_CODES) and never reused
MAX_FRAMES = 1000  # frame_NNN.jpg: three digits keep the names in driving order


def route_positions(city: City, rng: np.random.Generator, frames: int, spacing_m: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """A drive on the city's roads sampled every spacing_m metres along it -> (frames, 2) (east, north) metres and
    (frames,) travel headings, degrees clockwise from north in [0, 360); a frame on a corner has the new heading.
    The drive (road_graph.drive) follows a centreline and may turn onto the crossing road at a crossing; where its
    road ends (it leaves the tiles' area, or is built on) it turns back: a U-turn, the only way on when no crossing
    is left ahead. Only `rng` is drawn from."""
    graph = road_graph(city.place.world, city.place.roads, standing_half_span(city))
    path = drive(graph, rng, (frames - 1) * spacing_m)
    step = np.diff(path, axis=0)
    seg = np.linalg.norm(step, axis=1)
    start = np.concatenate([[0.0], np.cumsum(seg)])
    along = spacing_m * np.arange(frames)
    j = np.clip(np.searchsorted(start, along, side="right") - 1, 0, len(seg) - 1)  # a frame on a corner: outgoing
    positions = path[j] + ((along - start[j]) / seg[j])[:, None] * step[j]
    headings = np.degrees(np.arctan2(step[j, 0], step[j, 1])) % 360.0
    return positions, headings


def heading_change(headings: np.ndarray) -> np.ndarray:
    """(frames,) the turn from each frame's travel heading to the next frame's, degrees in (-180, 180], clockwise
    positive; 0 for frame 0."""
    turn = -((-np.diff(headings) + 180.0) % 360.0 - 180.0)
    return np.concatenate([[0.0], turn])


def odometry(headings: np.ndarray, spacing_m: float, rng: np.random.Generator, distance_noise: float,
             heading_noise_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """What the vehicle measures (module docstring) -> (frames,) distances and (frames,) heading changes."""
    n = len(headings)
    distance = spacing_m * rng.normal(1.0, distance_noise, n)
    turn = heading_change(headings) + rng.normal(0.0, heading_noise_deg, n)
    distance[0], turn[0] = 0.0, 0.0
    return distance, turn


def write_route(cfg: SynthConfig, city: City, seed: int, k: int, folder: Path, frames: int, spacing_m: float,
                distance_noise: float, heading_noise_deg: float) -> None:
    """Render and write route k of the city into `folder`, each file atomically."""
    r_route, r_odometry, *_ = city_rngs(seed, city.index, ROUTE_CODE, k, n=4)
    positions, headings = route_positions(city, r_route, frames, spacing_m)
    for i, (east, north) in enumerate(positions):
        jpeg = panorama_jpeg(cfg, city, frame_rngs(seed, city.index, k, i), float(east), float(north))
        LY.write_bytes(folder / f"frame_{i:03d}.jpg", jpeg)
    distance, turn = odometry(headings, spacing_m, r_odometry, distance_noise, heading_noise_deg)
    rows = [f"{i},{float(d)!r},{float(t)!r}" for i, (d, t) in enumerate(zip(distance, turn))]
    LY.write_bytes(folder / "odometry.csv", _csv("frame,distance_m,heading_change_deg", rows))
    latlon = offset_to_latlon(city.origin, positions[:, 0], positions[:, 1])
    rows = [",".join([str(i)] + [repr(float(v)) for v in (*latlon[i], *positions[i], headings[i])])
            for i in range(frames)]
    LY.write_bytes(folder / "truth.csv", _csv("frame,lat,lon,east_m,north_m,heading_deg", rows))


def frame_rngs(seed: int, city: int, k: int, i: int) -> list[np.random.Generator]:
    """render_panorama's (condition, traffic, sky, noise) streams for frame i of route k: the route's own condition
    and sky streams, new each frame (so one time of day and one sky for the whole drive), the frame's own traffic
    and noise."""
    _, _, r_cond, r_sky = city_rngs(seed, city, ROUTE_CODE, k, n=4)
    r_traffic, r_noise = city_rngs(seed, city, ROUTE_CODE, k, i, n=2)
    return [r_cond, r_traffic, r_sky, r_noise]


def _csv(header: str, rows: list[str]) -> bytes:
    return "".join(line + "\n" for line in [header, *rows]).encode()


def write_routes(root, cfg: SynthConfig, opts: VigorOptions, seed: int, count: int, frames: int = 20,
                 spacing_m: float = 10.0, distance_noise: float = 0.05, heading_noise_deg: float = 2.0,
                 workers: int = 1, overwrite: bool = False) -> Path:
    """Write `count` routes per city of the vigor world (cfg, opts, seed) into ROOT/routes (module docstring) ->
    that folder. A non-empty one is refused unless `overwrite`, which deletes it first. The files are the same
    whatever the number of workers."""
    _check(count=(count, 1, None), frames=(frames, 2, MAX_FRAMES), workers=(workers, 1, None), seed=(seed, 0, None))
    for name, value in (("spacing_m", spacing_m), ("distance_noise", distance_noise),
                        ("heading_noise_deg", heading_noise_deg)):
        if not (np.isfinite(value) and value >= 0) or (name == "spacing_m" and value == 0):
            raise ValueError(f"{name} must be a finite number >= 0 (spacing_m > 0), got {value!r}")
    out = Path(root) / ROUTES_DIR
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise ValueError(f"{out} is not empty: it holds routes already. Nothing was written; pass overwrite=True "
                             "(--overwrite) to replace them, or move the folder away")
        shutil.rmtree(out)
    jobs = [(cfg.as_dict(), asdict(opts), seed, c, k, str(out), frames, float(spacing_m), float(distance_noise),
             float(heading_noise_deg)) for c in range(opts.cities) for k in range(count)]
    if workers == 1:
        for job in jobs:
            _run(job)
    else:  # spawn, as generate.py: a forked child can deadlock in OpenCV's thread pool
        with mp.get_context("spawn").Pool(workers, initializer=cv2.setNumThreads, initargs=(1,)) as pool:
            list(pool.imap_unordered(_run, jobs))
    record = {"generator": "geoloc.synthetic.routes", "version": VERSION, "seed": seed, "count": count,
              "cities": list(CITY_NAMES[:opts.cities]), "frames": frames, "spacing_m": float(spacing_m),
              "distance_noise": float(distance_noise), "heading_noise_deg": float(heading_noise_deg),
              "config": cfg.as_dict(), "options": asdict(opts)}
    LY.write_bytes(out / ROUTES_FILE, (json.dumps(record, indent=1, sort_keys=True) + "\n").encode())
    return out


def _check(**values) -> None:
    """Each value an integer in [low, high] (high None: no bound), checked before anything is written."""
    for name, (value, low, high) in values.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < low or (high and value > high):
            raise ValueError(f"{name} must be an integer in [{low}, {high or 'inf'}], got {value!r}")


def _run(job) -> None:
    cfg_dict, opts_dict, seed, c, k, out, frames, spacing_m, distance_noise, heading_noise_deg = job
    cfg, opts = SynthConfig(**cfg_dict), VigorOptions(**opts_dict)
    city = build_city(cfg, opts.grid, seed, c)
    write_route(cfg, city, seed, k, Path(out) / city.name / f"route_{k:04d}", frames, spacing_m, distance_noise,
                heading_noise_deg)


USAGE = """python -m geoloc.synthetic.routes ROOT [--count 100] [--frames 20] [--spacing 10] [--workers 1] ...

ROOT is a synthetic vigor dataset (python data_prep/synthetic.py --layout vigor --out ROOT ...): its marker gives
the world (config, options, seed), so the routes drive the streets of its tiles."""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m geoloc.synthetic.routes", description=USAGE,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", help="a complete synthetic vigor dataset; the routes go to ROOT/routes")
    p.add_argument("--preset", default=None, help="check: the dataset's preset (default: whatever it is)")
    p.add_argument("--seed", type=int, default=None, help="check: the dataset's seed (default: whatever it is)")
    p.add_argument("--count", type=int, default=100, help="routes per city (default 100)")
    p.add_argument("--frames", type=int, default=20, help="panoramas per route (default 20)")
    p.add_argument("--spacing", type=float, default=10.0, help="metres driven between frames (default 10)")
    p.add_argument("--distance-noise", type=float, default=0.05, help="odometry distance: std of the factor")
    p.add_argument("--heading-noise", type=float, default=2.0, help="odometry heading change: std in degrees")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default 1); output is the same")
    p.add_argument("--overwrite", action="store_true", help="replace ROOT/routes if it holds routes")
    a = p.parse_args(argv)
    try:
        marker = vigor_marker(Path(a.root), "routes")
        for name, given in (("preset", a.preset), ("seed", a.seed)):
            if given is not None and given != marker[name]:
                raise ValueError(f"{a.root} was rendered with {name} {marker[name]!r}, not {given!r}: routes are "
                                 f"drawn in the dataset's own world, so leave --{name} out or give its value")
        out = write_routes(a.root, SynthConfig(**marker["config"]), VigorOptions(**marker["options"]),
                           int(marker["seed"]), a.count, a.frames, a.spacing, a.distance_noise, a.heading_noise,
                           a.workers, a.overwrite)
    except (ValueError, OSError) as err:
        p.exit(2, f"error: {err}\n")
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
