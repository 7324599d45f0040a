"""Synthetic generator speed: pairs/s per core at CVUSA size, a per-stage breakdown, the small preset end to end.

    python benchmarks/bench_synthetic.py [--pairs 12] [--small] [--workers 2]
    python benchmarks/bench_synthetic.py --against DIR [--preset small --pairs 60 --rounds 8]

--against: the default size (`small`, cvusa layout) timed in alternating rounds, the checkout at DIR (e.g. a worktree
of main) then this one, each round a fresh process of its own; prints each round's pairs/s per core and the ratio.

Per-core figures use CPU time of this process (one core, OMP_NUM_THREADS=1, cv2 single-threaded), so they mean
something on a shared machine; wall time is printed next to them. Nothing is asserted.
"""
import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
HERE = Path(__file__).resolve().parents[1]
if "--code" in sys.argv:  # the checkout whose geoloc is measured, before anything imports it
    HERE = Path(sys.argv[sys.argv.index("--code") + 1]).resolve()
sys.path.insert(0, str(HERE))

import cv2  # noqa: E402

from geoloc.synthetic import generate  # noqa: E402
from geoloc.synthetic.world_config import resolve  # noqa: E402
from geoloc.synthetic.layouts import encode  # noqa: E402
from geoloc.synthetic.samples import render_pair, render_place_views  # noqa: E402


def per_core(layout: str, preset: str, n: int) -> float:
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
          f"   {1000 * cpu / n:6.0f} ms CPU per sample", flush=True)
    return n / cpu


def against(other: Path, preset: str, pairs: int, rounds: int) -> None:
    """A B A B: the other checkout's and this one's pairs/s per core, each round in fresh processes."""
    def one(code: Path) -> float:
        out = subprocess.run([sys.executable, __file__, "--code", str(code), "--one", preset, "--pairs", str(pairs)],
                             check=True, capture_output=True, text=True).stdout
        return float(out.split()[2])
    ratios = []
    for r in range(rounds):
        a, b = one(other), one(Path(__file__).resolve().parents[1])
        ratios.append(b / a)
        print(f"round {r + 1}: {other.name} {a:6.2f}  this {b:6.2f} pairs/s per core   ratio {b / a:.3f}", flush=True)
    print(f"ratio this / {other}: median {statistics.median(ratios):.3f}, range {min(ratios):.3f}-{max(ratios):.3f} "
          f"over {rounds} rounds of {pairs} pairs (cvusa layout, preset {preset})")


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
    p.add_argument("--against", type=Path, help="another checkout: time it against this one, A B A B")
    p.add_argument("--preset", default="small", help="with --against: the cvusa preset timed")
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--code", type=Path, help=argparse.SUPPRESS)  # read above, before the imports
    p.add_argument("--one", help=argparse.SUPPRESS)  # one cvusa preset alone: a round of --against
    a = p.parse_args()
    cv2.setNumThreads(1)
    if a.one:
        per_core("cvusa", a.one, a.pairs)
        return
    if a.against:
        against(a.against.resolve(), a.preset, a.pairs, a.rounds)
        return
    print(f"load average at start: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    per_core("cvusa", "cvusa", a.pairs)
    per_core("cvusa", "small", 3 * a.pairs)
    per_core("cvact", "cvact", max(2, a.pairs // 3))
    per_core("dynamic", "dynamic_small", a.pairs)
    if a.small:
        small_end_to_end(a.workers)


if __name__ == "__main__":
    main()
