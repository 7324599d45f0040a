"""Polar transforms: cached cv2.remap grids against a direct, vectorised numpy evaluation of the same formula.

The baseline evaluates the formula of docs/conventions.md "Polar transform" for every output pixel and samples
bilinearly with numpy fancy indexing (no Python loop), as a plain numpy implementation would on every call. The
target is >= 20x.

    OMP_NUM_THREADS=1 python benchmarks/bench_polar.py [--repeats 20] [--threads 1]
"""
import argparse
import math
import os
import time

import cv2
import numpy as np

from geoloc.data.polar import aerial_to_polar, street_to_aerial


def bilinear_numpy(img, row, col, wrap_cols=False):
    h, w = img.shape[:2]
    r0, c0 = np.floor(row).astype(np.int64), np.floor(col).astype(np.int64)
    fr, fc = (row - r0)[..., None], (col - c0)[..., None]
    out = np.zeros(row.shape + img.shape[2:], np.float64)
    for rr, wr in ((r0, 1 - fr), (r0 + 1, fr)):
        for cc, wc in ((c0, 1 - fc), (c0 + 1, fc)):
            if wrap_cols:
                cc = cc % w
            ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
            out += np.where(ok[..., None], wr * wc * img[np.clip(rr, 0, h - 1), np.clip(cc, 0, w - 1)], 0)
    return np.clip(np.rint(out), 0, 255).astype(img.dtype)


def polar_numpy(img, out_hw):
    s, (h, w) = img.shape[0], out_hw
    i, j = np.mgrid[0:h, 0:w].astype(np.float64)
    r = (s / 2) / h * (h - 1 - i)
    theta = 2 * np.pi * j / w
    return bilinear_numpy(img, s / 2 + r * np.cos(theta), s / 2 - r * np.sin(theta))


def ipt_numpy(img, out_hw):
    (h_s, w_s), (h_a, w_a) = img.shape[:2], out_hw
    y, x = np.mgrid[0:h_a, 0:w_a].astype(np.float64)
    y, x = y - h_a / 2, x - w_a / 2
    r = np.hypot(x, y)
    row = (h_s - 1) - math.sqrt(2) * (h_s / h_a) * r
    col = w_s * np.mod(np.arctan2(-x, y), 2 * np.pi) / (2 * np.pi)
    return bilinear_numpy(img, row, col, wrap_cols=True)


def best_ms(fn, repeats):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1000 * min(times), 1000 * float(np.median(times))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=1, help="cv2 threads (numpy's baseline uses one)")
    args = parser.parse_args()
    cv2.setNumThreads(args.threads)
    rng = np.random.default_rng(0)
    aerial = rng.integers(0, 256, (750, 750, 3), dtype=np.uint8)
    street = rng.integers(0, 256, (224, 1232, 3), dtype=np.uint8)
    cases = [
        ("aerial_to_polar 750x750 -> 112x616", lambda: aerial_to_polar(aerial, (112, 616)),
         lambda: polar_numpy(aerial, (112, 616))),
        ("street_to_aerial 1232x224 -> 288x288", lambda: street_to_aerial(street, (288, 288)),
         lambda: ipt_numpy(street, (288, 288))),
    ]
    print(f"cv2 threads {cv2.getNumThreads()}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '-')}, "
          f"best / median of {args.repeats}")
    print(f"{'transform':40s} {'remap ms':>16s} {'numpy ms':>16s} {'ratio':>8s}")
    for name, fast, slow in cases:
        fast()  # builds and caches the grid
        diff = np.abs(fast().astype(int) - slow().astype(int))
        f_best, f_med = best_ms(fast, args.repeats)
        s_best, s_med = best_ms(slow, max(3, args.repeats // 4))
        print(f"{name:40s} {f_best:7.2f} / {f_med:6.2f} {s_best:7.2f} / {s_med:6.2f} {s_med / f_med:7.1f}x"
              f"   (max |diff| {diff.max()}, mean {diff.mean():.3f})")


if __name__ == "__main__":
    main()
