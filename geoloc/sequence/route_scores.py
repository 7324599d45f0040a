"""How well the sequence filter does on routes whose truth is known: the figures docs/sequence.md reports, computed
one way for the simulation (benchmarks/bench_sequence.py), for rendered routes answered by a model
(tools/evaluate_routes.py) and for choosing q on held-out routes (fit.py).

For a set of routes (RouteCase: each frame's answer, the odometry, the true positions and the frame's own single
answer), at the last frame:
- single: the share of all frames whose own answer is within `radius_m` of the truth (the top-1 tile centre, or
  the refined top-1 where a refiner ran);
- last: the share of routes whose filtered position is within `radius_m`; ratio = last / single;
- region, ellipse: the share of routes whose 95% highest-density region (FrameEstimate.contains) or 95% Gaussian
  ellipse (in_ellipse) holds the truth; region_ha, ellipse_ha: their median areas in hectares;
- recover: of the routes with a frame before the last whose own answer is more than `wrong_m` off, the share
  within `radius_m` at the last frame; first_wrong: the same for routes whose first frame's answer is (nan where
  no route qualifies);
- ms_per_frame: the filter's step and estimate, wall time per frame.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from geoloc.sequence.measurement import FrameAnswer
from geoloc.sequence.odometry import Odometry
from geoloc.sequence.particle_filter import FilterConfig, localize_route


@dataclass(frozen=True)
class RouteCase:
    """One route with its truth: answers (F FrameAnswers), odometry (F rows), truth (F, 2) metres on the answers'
    plane, single (F, 2) each frame's own answer on that plane (None: the top-1 tile centre)."""

    answers: list[FrameAnswer]
    odometry: Odometry
    truth: np.ndarray
    single: np.ndarray | None = None

    def own_answers(self) -> np.ndarray:
        """(F, 2) each frame's own answer: `single`, or the top-1 tile centre."""
        if self.single is not None:
            return np.asarray(self.single, np.float64)
        return np.stack([answer.centres[0] for answer in self.answers])


@dataclass(frozen=True)
class RouteScores:
    """The module docstring's figures for one set of routes and one filter setting; routes: how many."""

    routes: int
    single: float
    last: float
    region: float
    region_ha: float
    ellipse: float
    ellipse_ha: float
    recover: float
    first_wrong: float
    ms_per_frame: float

    @property
    def ratio(self) -> float:
        return self.last / self.single if self.single > 0 else float("nan")


def _share(flags: list[bool]) -> float:
    return float(np.mean(flags)) if flags else float("nan")


def score_routes(cases: Sequence[RouteCase], extent, config: FilterConfig,
                 seed_of: Callable[[int], int] = lambda r: r, radius_m: float = 25.0, wrong_m: float = 50.0,
                 level: float = 0.95) -> RouteScores:
    """Every route filtered with `config` over `extent` (the filter's GalleryExtent or RegionsExtent), route r with
    seed seed_of(r), and scored at its last frame."""
    if not cases:
        raise ValueError("scoring routes needs at least one route")
    single, last, region, area, ellipse, ellipse_area, recover, first_wrong = [], [], [], [], [], [], [], []
    seconds, frames = 0.0, 0
    for r, case in enumerate(cases):
        start = time.perf_counter()
        estimate = localize_route(case.answers, case.odometry, extent, config, seed=seed_of(r))[-1]
        seconds += time.perf_counter() - start
        frames += len(case.answers)
        own = np.hypot(*(case.own_answers() - case.truth).T)
        truth = case.truth[-1]
        found = bool(np.hypot(*(estimate.position - truth)) <= radius_m)
        single += list(own <= radius_m)
        last.append(found)
        region.append(estimate.contains(truth, level))
        area.append(estimate.region_area_m2(level) / 1e4)
        ellipse.append(estimate.in_ellipse(truth, level))
        ellipse_area.append(estimate.ellipse_area_m2(level) / 1e4)
        if (own[:-1] > wrong_m).any():
            recover.append(found)
        if own[0] > wrong_m:
            first_wrong.append(found)
    return RouteScores(len(cases), _share(single), _share(last), _share(region), float(np.median(area)),
                       _share(ellipse), float(np.median(ellipse_area)), _share(recover), _share(first_wrong),
                       1000 * seconds / frames)
