"""The start-up file check (`dataset.check_files=decode`): full-size decodes against worker count, and a cached start.

Writes --n CVUSA-sized JPEGs (half 750x750 aerial tiles, half 1232x224 panoramas, quality 95, of smooth noise so
they compress like photos) into a temporary folder, then times:
- the old check: a 1/8-scale greyscale decode (it misses truncation);
- the new check (byte checks + full-size decode) with 1, 2, 4 and 8 threads;
- a second start, which finds every file in the cache and only stats it.

    python benchmarks/bench_file_check.py --n 300
"""
import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from geoloc.data import validate  # noqa: E402


def write_images(folder: Path, n: int) -> list[Path]:
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        h, w = (750, 750) if i % 2 == 0 else (224, 1232)
        small = rng.integers(0, 255, (h // 8 + 1, w // 8 + 1, 3), np.uint8)
        img = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
        path = folder / f"{i:05d}.jpg"
        cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        paths.append(path)
    return paths


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=300)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        os.environ["GEOLOC_CACHE"] = str(tmp / "cache")
        (tmp / "img").mkdir()
        paths = write_images(tmp / "img", args.n)
        mb = sum(p.stat().st_size for p in paths) / 2**20
        print(f"{args.n} JPEGs, {mb:.0f} MiB, on {os.cpu_count()} CPUs")
        old = timed(lambda: [cv2.imread(str(p), cv2.IMREAD_REDUCED_GRAYSCALE_8) for p in paths])
        print(f"old 1/8-scale check, 1 thread: {old:.2f} s")
        for workers in (1, 2, 4, 8):
            split = f"bench{workers}"  # a fresh cache record per run
            t = timed(lambda: validate.check_files(paths, tmp / "img", split, workers=workers))
            print(f"full check, {workers} thread(s): {t:.2f} s ({args.n / t:.0f} images/s)")
        again = timed(lambda: validate.check_files(paths, tmp / "img", "bench8"))
        print(f"second start (cached): {again * 1000:.0f} ms")


if __name__ == "__main__":
    main()
