"""Synthetic generator speed: pairs/s per core at CVUSA size, a per-stage breakdown, the small preset end to end.

    python benchmarks/bench_synthetic.py [--pairs 12] [--small] [--workers 2]

Per-core figures use CPU time of this process (one core, OMP_NUM_THREADS=1, cv2 single-threaded), so they mean
something on a shared machine; wall time is printed next to them. Nothing is asserted.
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
from geoloc.synthetic.world_config import resolve  # noqa: E402
from geoloc.synthetic.layouts import encode  # noqa: E402
from geoloc.synthetic.samples import render_pair, render_place_views  # noqa: E402


def per_core(layout: str, preset: str, n: int) -> None:
    cfg, _ = resolve(layout, preset, {})
    render = (lambda i: render_place_views(cfg, 0, "train", i)) if layout == "dynamic" else (
        lambda i: render_pair(cfg, 0, "train", i, sphere=layout == "cvact"))
    render(10_000)  # warm caches (noise field, imports)
    cpu, wall = time.process_time(), time.perf_counter()
    for i in range(n):
        out = render(i)
        if layout != "dynamic":
            encode(out["aerial"], ".jpg", 90)
            encode(out["pano"], ".jpg", 90)
            encode(out["pano_labels"], ".png")
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    unit = "places" if layout == "dynamic" else "pairs"
    print(f"{layout:8s} preset={preset:14s} {n / cpu:6.2f} {unit}/s per core (CPU)   {n / wall:6.2f} {unit}/s wall"
          f"   {1000 * cpu / n:6.0f} ms CPU per sample")


def small_end_to_end(workers: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        generate("cvusa", Path(tmp) / "small", preset="small", workers=workers, progress=True)
        dt = time.perf_counter() - t
    print(f"small preset (cvusa layout, 1200 + 300 pairs, 256 px aerial, 616x112 pano): {dt:.1f} s wall "
          f"with {workers} workers; load average now {os.getloadavg()[0]:.2f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pairs", type=int, default=12)
    p.add_argument("--small", action="store_true", help="also time the whole small preset")
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args()
    cv2.setNumThreads(1)
    print(f"load average at start: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    per_core("cvusa", "cvusa", a.pairs)
    per_core("cvusa", "small", 3 * a.pairs)
    per_core("cvact", "cvact", max(2, a.pairs // 3))
    per_core("dynamic", "dynamic_small", a.pairs)
    if a.small:
        small_end_to_end(a.workers)


if __name__ == "__main__":
    main()
