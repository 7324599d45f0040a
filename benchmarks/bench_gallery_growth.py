"""Recall within 25 / 50 / 100 m as the gallery grows: one trained checkpoint's street frames against its gallery's
tiles plus N tiles of other synthetic cities, the rest of a region that holds none of the frames.

    python benchmarks/bench_gallery_growth.py ROUTES --runs CKPT GALLERY [CKPT GALLERY ...]
        [--sizes 0 1000 10000 100000] [--grid 32] [--heading 0] [--out growth.json]

- CKPT GALLERY pairs (seeds of one recipe, say): the added tiles are rendered once and encoded by each.
- GALLERY: a saved gallery with positions (`evaluate.py ckpt=CKPT dataset=vigor gallery.save=DIR`); its tiles are
  read from its root and encoded by CKPT's reference branch as the gallery build encodes them.
- ROUTES: a synthetic routes folder (`python -m geoloc.synthetic.routes ROOT`): every route_*/frame_NNN.jpg is a
  query at its truth.csv position, encoded with the heading given (routes' panoramas are north-aligned: 0).
- The added tiles: synthetic VIGOR cities of `--grid` x `--grid` half-overlapping tiles (the gallery's preset:
  tile extent, size, appearance), each drawn from its own seed (1000 + i), rendered as the layout renders a city's
  satellite tiles and encoded as PNG-decoded tiles are (PNG is lossless). They stand for the rest of a state: they
  lie in no frame's neighbourhood, so a frame whose top-1 is one of them is a miss at every radius.
- For each size N: the share of frames whose top-1 tile centre (over the gallery and the first N added tiles, exact
  inner products) lies within 25, 50 and 100 m of the frame's truth. N = 0 is the gallery alone, and equals what
  localize.py answers for the same frames.

Prints one markdown table and the seconds spent rendering and encoding. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from geoloc.data.geo import haversine_m
from geoloc.data.io import read_rgb
from geoloc.gallery.places import read_places
from geoloc.synthetic.city import build_city, render_tiles
from geoloc.synthetic.world_config import resolve
from geoloc.tasks.crossview.encoder import CrossViewEncoder
from geoloc.tasks.crossview.transforms import decode_size

RADII_M = (25.0, 50.0, 100.0)
BATCH = 256


def encode_tiles(encoders: list[CrossViewEncoder], tiles) -> list[torch.Tensor]:
    """Each encoder's (N, dim) reference descriptors of an iterable of H×W×3 uint8 RGB tiles, in batches."""
    out, batch = [[] for _ in encoders], []

    def flush():
        for encoder, done in zip(encoders, out):
            done.append(encoder.encode_aerial(torch.cat([encoder.aerial_input(tile) for tile in batch])))
        batch.clear()

    for tile in tiles:
        batch.append(tile)
        if len(batch) == BATCH:
            flush()
    if batch:
        flush()
    return [torch.cat(done) if done else torch.empty(0, 0) for done in out]


def gallery_tiles(encoder: CrossViewEncoder, gallery: Path) -> tuple[torch.Tensor, np.ndarray]:
    """The saved gallery's tiles (read and checked as the localizer reads them) encoded, and their (lat, lon)."""
    places = read_places(gallery, json.loads((gallery / "gallery.json").read_text()))
    if places.kind != "latlon":
        raise SystemExit(f"{gallery}: the routes' truths are lat/lon, but this gallery's positions are {places.kind}")
    size = decode_size(encoder.data, "aerial")
    descriptors = encode_tiles([encoder], (read_rgb(places.root / path, size) for path in places.references))[0]
    return descriptors, places.reference_positions


def route_frames(encoder: CrossViewEncoder, routes: Path, heading: float) -> tuple[torch.Tensor, np.ndarray]:
    """Every frame of every route under `routes`, encoded, and its true (lat, lon)."""
    descriptors, truths = [], []
    for route in sorted(p for p in routes.glob("*/route_*") if p.is_dir()):
        truth = np.genfromtxt(route / "truth.csv", delimiter=",", names=True)
        for i in range(len(truth)):
            inputs, _ = encoder.street_inputs(read_rgb(route / f"frame_{i:03d}.jpg"), 360.0, heading)
            descriptors.append(encoder.encode_street(inputs))
            truths.append([float(truth["lat"][i]), float(truth["lon"][i])])
    return torch.cat(descriptors), np.array(truths)


def city_tiles(preset: str, grid: int, count: int):
    """`count` tiles of synthetic cities of the preset, grid x grid each, city i from seed 1000 + i."""
    cfg, _ = resolve("vigor", preset, {})
    made, i = 0, 0
    while made < count:
        city = build_city(cfg, grid, 1000 + i, i % 4)
        for _, _, rgb in render_tiles(cfg, city, 1000 + i):
            if made == count:
                return
            made += 1
            yield rgb
        i += 1


def within(queries: torch.Tensor, gallery: torch.Tensor, positions: np.ndarray, added: torch.Tensor,
           truths: np.ndarray) -> list[float]:
    """Shares of queries whose top-1 over gallery ∪ added is a gallery tile within each radius of the truth."""
    q = queries
    best_score, best_row = (q @ gallery.T).max(1)
    if len(added):
        added_best = torch.full_like(best_score, -torch.inf)
        for start in range(0, len(added), 65536):
            added_best = torch.maximum(added_best, (q @ added[start:start + 65536].T).max(1).values)
        real = best_score >= added_best  # ties go to the gallery tile: a real tile listed first
    else:
        real = torch.ones_like(best_score, dtype=torch.bool)
    error = haversine_m(positions[best_row.numpy()], truths)
    return [float(np.mean(real.numpy() & (error <= r))) for r in RADII_M]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("routes", type=Path)
    p.add_argument("--runs", nargs="+", required=True, help="CKPT GALLERY pairs")
    p.add_argument("--sizes", type=int, nargs="+", default=[0, 1000, 10000, 100000])
    p.add_argument("--grid", type=int, default=32, help="each added city's tiles a side")
    p.add_argument("--preset", default="vigor_small", help="the synthetic preset of the added cities")
    p.add_argument("--heading", type=float, default=0.0)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    if len(args.runs) % 2:
        p.error("--runs takes CKPT GALLERY pairs")
    pairs = [(args.runs[i], Path(args.runs[i + 1])) for i in range(0, len(args.runs), 2)]
    encoders = [CrossViewEncoder.load(ckpt, use="bench_gallery_growth", device="cpu") for ckpt, _ in pairs]
    t0 = time.perf_counter()
    runs = []
    for encoder, (_, gallery) in zip(encoders, pairs):
        runs.append((*gallery_tiles(encoder, gallery), *route_frames(encoder, args.routes, args.heading)))
    t1 = time.perf_counter()
    added = encode_tiles(encoders, city_tiles(args.preset, args.grid, max(args.sizes)))
    t2 = time.perf_counter()
    table = {n: [within(queries, gallery, positions, extra[:n], truths)
                 for (gallery, positions, queries, truths), extra in zip(runs, added)] for n in sorted(args.sizes)}
    print(f"| gallery tiles | added tiles | {' | '.join(f'within {r:g} m' for r in RADII_M)} |")
    print("|---|---|" + "---|" * len(RADII_M))
    for n, shares in table.items():
        cells = []
        for j in range(len(RADII_M)):
            values = 100 * np.array([s[j] for s in shares])
            spread = f" ± {values.std(ddof=1):.2f}" if len(values) > 1 else ""
            cells.append(f"{values.mean():.2f}{spread}% ({' / '.join(f'{v:.2f}' for v in values)})")
        print(f"| {len(runs[0][0]) + n:,} | {n:,} | " + " | ".join(cells) + " |")
    print(f"{len(runs[0][2])} frames, {len(pairs)} checkpoints; galleries and frames encoded in {t1 - t0:.0f} s; "
          f"{max(args.sizes):,} added tiles rendered and encoded in {t2 - t1:.0f} s ({torch.get_num_threads()} "
          "threads)")
    if args.out is not None:
        args.out.write_text(json.dumps({"runs": [[c, str(g)] for c, g in pairs], "frames": len(runs[0][2]),
                                        "grid": args.grid, "radii_m": RADII_M,
                                        "rows": {n: shares for n, shares in table.items()}}, indent=2))


if __name__ == "__main__":
    main()
