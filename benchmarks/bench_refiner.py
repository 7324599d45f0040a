"""The correlation refiner's cost: one query refined in its top-5 tiles (encode the query, encode 5 tiles, match),
on one thread, at the refiner's input sides and with a known heading (1 bin) or an unknown one (12 or 36 bins).

    OMP_NUM_THREADS=1 python benchmarks/bench_refiner.py [--sides 64 128 256] [--bins 1 12 36] [--tiles 5] [--repeats 20]
        [--overlap mean|window] [--query-scale 1.13] [--kernel-frac 1.0] [--context 1] [--peak-smoothing 0.04]
        [--cpu-precision bf16] [--margin 0.25]

Prints the median milliseconds of each setting, and the tile encoding alone (what a gallery could store once).
--query-scale S matches with the ground scale as an input (the query's map drawn S times larger for every tile, as
refiner.query_extent_m does for tiles of one extent); 0 (the default) without it. --kernel-frac and --context are
refiner.kernel_frac (the share of the query map's side matched) and refiner.context (extra dilated blocks in each
encoder); the query's time includes reading each tile's answer (its position and mass within 5 m) with
--peak-smoothing (refiner.peak_smoothing); --cpu-precision bf16 encodes under bfloat16 autocast, as a checkpoint
trained with trainer.cpu_precision=bf16 is evaluated and served on the CPU (the matching stays float32). --margin M
is refiner.margin: each tile read with M of its side beyond each edge (4 channels, side + 2 round(M side / 2) * 2
pixels across), the tiles already stitched (their reading is not timed).
experiment=refine_vigor is --widths 32 --sides 128 --bins 1 --kernel-frac 1.0 --context 1 --peak-smoothing 0.04
--cpu-precision bf16."""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from geoloc import registry
from geoloc.data.tile_context import stitched_side
from geoloc.engine.device import autocast
import geoloc.models.refiners  # noqa: F401


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1000)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sides", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--tiles", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--bins", type=int, nargs="+", default=[1, 12, 36], help="heading bins (1: known heading)")
    parser.add_argument("--widths", type=int, nargs="+", default=[16, 32],
                        help="refiner.width = refiner.channels (16: the default, 32: the refine_vigor recipe)")
    parser.add_argument("--overlap", default="mean", choices=["mean", "window"])
    parser.add_argument("--query-scale", type=float, default=0.0)
    parser.add_argument("--kernel-frac", type=float, default=0.5, help="refiner.kernel_frac")
    parser.add_argument("--context", type=int, default=0, help="refiner.context")
    parser.add_argument("--peak-smoothing", type=float, default=0.0, help="refiner.peak_smoothing")
    parser.add_argument("--cpu-precision", default="32", choices=["32", "bf16"], help="trainer.cpu_precision")
    parser.add_argument("--margin", type=float, default=0.0, help="refiner.margin")
    args = parser.parse_args()
    scale = torch.full((args.tiles,), args.query_scale) if args.query_scale else None
    extent = torch.full((args.tiles, 2), 72.96)  # metres: the synthetic VIGOR tile
    torch.set_num_threads(args.threads)
    print(f"| width | side | headings | query + {args.tiles} tiles (ms) | {args.tiles} tiles encoded (ms) | match (ms) |")
    print("|---|---|---|---|---|---|")
    for width, side in ((w, s) for w in args.widths for s in args.sides):
        refiner = registry.build("refiner", {"name": "correlation", "width": width, "channels": width,
                                             "overlap": args.overlap, "kernel_frac": args.kernel_frac,
                                             "context": args.context}).eval()
        wide = stitched_side(side, args.margin)
        query = torch.randn(1, 3, side, side)
        tiles = torch.randn(args.tiles, 4 if args.margin else 3, wide, wide)
        if args.margin:
            tiles[:, 3] = 1.0  # covered everywhere

        def encoded_query():
            with autocast("32", torch.device("cpu"), args.cpu_precision):
                return refiner.encode_query(query).float()

        def encoded_tiles():
            with autocast("32", torch.device("cpu"), args.cpu_precision):
                return refiner.encode_reference(tiles).float()

        for bins in args.bins:
            headings = torch.arange(bins) * (360.0 / bins)

            @torch.no_grad()
            def whole():
                out = refiner.match(encoded_query().expand(args.tiles, -1, -1, -1), encoded_tiles(), headings, scale)
                out.position(args.peak_smoothing)
                out.mass_within(5.0, extent, args.peak_smoothing)

            with torch.no_grad():
                encoded = encoded_tiles()
                maps = encoded_query().expand(args.tiles, -1, -1, -1)
                tile_ms = median_ms(encoded_tiles, args.repeats)
                match_ms = median_ms(lambda: refiner.match(maps, encoded, headings, scale), args.repeats)
            print(f"| {width} | {side} | {bins} | {median_ms(whole, args.repeats):.1f} | {tile_ms:.1f} | "
                  f"{match_ms:.1f} |", flush=True)


if __name__ == "__main__":
    main()
