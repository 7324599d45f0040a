"""The sequence filter (geoloc/sequence/) in simulation: how much more often a 20-frame route is localised than its
single frames, how honest its 95% region is, how often it recovers from wrong answers, and its cost per frame.

    OMP_NUM_THREADS=1 python benchmarks/bench_sequence.py [--hit-probs 0.1 0.3 0.5] [--seeds 0 1 2] [--routes 200]
        [--particles 5000] [--tile-sigma 25] [--wrong-answer-prob Q]

Each route is geoloc.sequence.simulation's: 20 frames 10 m apart over a 2 km x 2 km gallery of 70 m tiles on a 35 m
lattice; each frame's top-5 holds a right tile with probability p (the hit rate), else five random tiles. The filter
is told the simulation's score temperature and odometry noise, and q = 1 - p unless --wrong-answer-prob is given.
Per hit rate, the mean ± standard deviation over the seeds (each seed: its own routes and filter draws) of:
- single within 25 m: the share of frames whose top-1 tile centre is within 25 m of the truth;
- last within 25 m: the share of routes whose last-frame estimate is;
- region: the share of routes whose last-frame 95% highest-density region holds the truth; area: the median area
  of that region, in hectares (the whole gallery is 426 ha); ellipse, ellipse area: the same for the Gaussian 95%
  ellipse;
- recover: of the routes with a frame before the last whose top-1 is more than 50 m off, the share within 25 m at
  the last frame (first wrong: of the routes whose first frame's top-1 is);
- ms / frame: the filter's step and estimate, on one thread (set OMP_NUM_THREADS=1).
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np

from geoloc.sequence import FilterConfig, SimulatedGallery, SimulationConfig
from geoloc.sequence.route_scores import RouteCase, score_routes

COLUMNS = ("single within 25 m", "last within 25 m", "ratio", "region", "area (ha)", "ellipse", "ellipse area (ha)",
           "recover", "first wrong: recover", "ms / frame")


def run(hit_prob: float, seed: int, args) -> dict:
    """One seed's figures at one hit rate."""
    simulation = SimulationConfig(hit_prob=hit_prob)
    gallery = SimulatedGallery(simulation)
    config = FilterConfig(particles=args.particles, tile_sigma_m=args.tile_sigma,
                          wrong_answer_prob=args.wrong_answer_prob or 1 - hit_prob,
                          temperature=simulation.matched_temperature, distance_sigma=simulation.distance_noise,
                          heading_sigma_deg=simulation.heading_noise_deg)
    rng = np.random.default_rng(1000 + seed)
    cases = [RouteCase(route.answers, route.odometry, route.truth)
             for route in (gallery.route(rng) for _ in range(args.routes))]
    s = score_routes(cases, gallery.extent, config, seed_of=lambda r: seed * 100_000 + r)
    return dict(zip(COLUMNS, (s.single, s.last, s.ratio, s.region, s.region_ha, s.ellipse, s.ellipse_ha, s.recover,
                              s.first_wrong, s.ms_per_frame)))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--hit-probs", type=float, nargs="+", default=[0.1, 0.3, 0.5])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--routes", type=int, default=200)
    parser.add_argument("--particles", type=int, default=FilterConfig.particles)
    parser.add_argument("--tile-sigma", type=float, default=FilterConfig.tile_sigma_m)
    parser.add_argument("--wrong-answer-prob", type=float, default=None, help="q; default 1 - the hit rate")
    args = parser.parse_args()
    print(f"{args.routes} routes x {len(args.seeds)} seeds per hit rate; particles {args.particles}, tile_sigma_m "
          f"{args.tile_sigma}, wrong_answer_prob {args.wrong_answer_prob or '1 - p'}")
    print("| p | " + " | ".join(COLUMNS) + " |")
    print("|---" * (len(COLUMNS) + 1) + "|")
    for hit_prob in args.hit_probs:
        runs = [run(hit_prob, seed, args) for seed in args.seeds]
        cells = []
        for column in COLUMNS:
            values = [r[column] for r in runs]
            spread = statistics.stdev(values) if len(values) > 1 else 0.0
            digits = 1 if column in ("ratio", "ms / frame") else 2 if "area" in column else 3
            cells.append(f"{statistics.mean(values):.{digits}f} ± {spread:.{digits}f}")
        print(f"| {hit_prob} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
