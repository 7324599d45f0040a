"""Speed of the vigor and u1652 synthetic layouts: CPU time per city world, per city's tiles, per panorama and
per building, and optionally a whole small preset end to end.

    python benchmarks/bench_synthetic_layouts.py [--panoramas 12] [--buildings 4] [--end-to-end]

Per-core figures use CPU time of this process (one core, OMP_NUM_THREADS=1, cv2 single-threaded), so they mean
something on a shared machine. Nothing is asserted.
"""
import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402

from geoloc.synthetic import generate  # noqa: E402
from geoloc.synthetic.city import (build_city, city_rngs, panorama_position,  # noqa: E402
                                        render_panorama, render_tiles)
from geoloc.synthetic.world_config import resolve, resolve_options  # noqa: E402
from geoloc.synthetic.drone import render_building  # noqa: E402
from geoloc.synthetic.layouts import encode  # noqa: E402


def _cpu(fn):
    t = time.process_time()
    out = fn()
    return out, time.process_time() - t


def vigor(preset: str, panoramas: int) -> None:
    cfg, _ = resolve("vigor", preset, {})
    opts = resolve_options("vigor", preset, {})
    city, t_world = _cpu(lambda: build_city(cfg, opts.grid, 0, 0))
    tiles, t_tiles = _cpu(lambda: [encode(rgb, ".png") for _, _, rgb in render_tiles(cfg, city, 0)])

    def panos():
        for k in range(panoramas):
            r_pos, *rngs = city_rngs(0, 0, 1, k)
            out = render_panorama(cfg, city, rngs, *panorama_position(city, r_pos))
            encode(out["pano"], ".jpg", 90)

    _, t_panos = _cpu(panos)
    print(f"vigor preset={preset}: city world {opts.grid}x{opts.grid} tiles ({city.place.world.n} cells a side) "
          f"{t_world:.2f} s CPU; its {len(tiles)} tiles {t_tiles:.2f} s; {1000 * t_panos / panoramas:.0f} ms CPU per "
          f"{cfg.sphere_width}x{cfg.sphere_height} panorama")


def u1652(preset: str, buildings: int) -> None:
    cfg, _ = resolve("u1652", preset, {})
    opts = resolve_options("u1652", preset, {})

    def run():
        for k in range(buildings):
            b = render_building(cfg, opts.drone_views, 0, 1, k)
            encode(b["satellite"], ".jpg", 90)
            for img in b["drone"]:
                encode(img, ".jpg", 90)

    _, t = _cpu(run)
    print(f"u1652 preset={preset}: {1000 * t / buildings:.0f} ms CPU per building (satellite {cfg.aerial_size} px + "
          f"{opts.drone_views} drone views of {cfg.view_size} px)")


def end_to_end(layout: str, preset: str, workers: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        generate(layout, Path(tmp) / "ds", preset=preset, workers=workers, progress=False)
        dt = time.perf_counter() - t
    print(f"{layout} preset={preset} end to end: {dt:.1f} s wall with {workers} workers; "
          f"load average now {os.getloadavg()[0]:.2f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--panoramas", type=int, default=12)
    p.add_argument("--buildings", type=int, default=4)
    p.add_argument("--end-to-end", action="store_true", help="also time vigor_small and u1652_small whole")
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args()
    cv2.setNumThreads(1)
    print(f"load average at start: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    vigor("vigor_small", a.panoramas)
    u1652("u1652_small", a.buildings)
    if a.end_to_end:
        end_to_end("vigor", "vigor_small", a.workers)
        end_to_end("u1652", "u1652_small", a.workers)


if __name__ == "__main__":
    main()
