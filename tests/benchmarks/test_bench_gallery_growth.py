"""benchmarks/bench_gallery_growth.py: the share within each radius as tiles are added, against a brute-force loop
over every frame and tile, and the added cities' tiles as the vigor layout renders them."""

import importlib.util

import numpy as np
import torch
from conftest import REPO

from geoloc.data.geo import haversine_m, offset_to_latlon
from geoloc.synthetic.city import build_city, render_tiles
from geoloc.synthetic.world_config import resolve

spec = importlib.util.spec_from_file_location("bench_gallery_growth", REPO / "benchmarks" / "bench_gallery_growth.py")
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)


def brute_within(queries, gallery, positions, added, truths, radius):
    hits = 0
    for q, truth in zip(queries, truths):
        scores = [float(q @ g) for g in gallery]
        best = int(np.argmax(scores))  # the first of equal scores, as torch.max takes
        if any(float(q @ a) > scores[best] for a in added):
            continue  # an added tile lies in no frame's neighbourhood: a miss at every radius
        hits += haversine_m(positions[best], truth) <= radius
    return hits / len(queries)


def test_within_is_the_brute_force_share():
    rng = np.random.default_rng(0)
    origin = (41.8781, -87.6298)
    positions = offset_to_latlon(origin, rng.uniform(0, 300, 40), rng.uniform(0, 300, 40))
    truths = offset_to_latlon(origin, rng.uniform(0, 300, 60), rng.uniform(0, 300, 60))
    gallery, queries = torch.randn(40, 8), torch.randn(60, 8)
    added = torch.randn(500, 8) * 0.9
    for n in (0, 10, 500):
        shares = bench.within(queries, gallery, positions, added[:n], truths)
        expect = [brute_within(queries, gallery, positions, added[:n], truths, r) for r in bench.RADII_M]
        assert np.allclose(shares, expect)
    assert shares[2] < bench.within(queries, gallery, positions, added[:0], truths)[2]  # added tiles cost hits


def test_added_tiles_are_the_layouts_city_tiles():
    tiles = list(bench.city_tiles("vigor_small", 2, 6))  # cities of 2 x 2 tiles: 4 of seed 1000, 2 of seed 1001
    cfg, _ = resolve("vigor", "vigor_small", {})
    first = [rgb for _, _, rgb in render_tiles(cfg, build_city(cfg, 2, 1000, 0), 1000)]
    second = [rgb for _, _, rgb in render_tiles(cfg, build_city(cfg, 2, 1001, 1), 1001)]
    assert len(tiles) == 6 and all(t.shape == (cfg.aerial_size, cfg.aerial_size, 3) for t in tiles)
    assert all(np.array_equal(a, b) for a, b in zip(tiles, first + second[:2]))
