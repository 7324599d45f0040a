"""The filter's settings fitted from held-out data with known positions: its answer model from single-image answers,
and the settings that keep its region calibrated from held-out routes.

A frame's measurement (measurement.py, particle_filter.py) has two numbers that belong to the gallery and the model
rather than to the route:
- wrong_answer_prob q: the chance that no tile of a frame's top-k is near the camera. Fitted as the share of held-out
  answers whose top-k holds no tile centre within `radius_m` of the truth (1 - the top-k hit rate at that radius);
- temperature: the softmax temperature s^2 / (m_1 - m_0) of the tile weights, for right-tile scores N(m_1, s^2) and
  wrong-tile scores N(m_0, s^2). Fitted from the same answers: m_1 and m_0 the mean scores of the near and the other
  tiles, s^2 their pooled within-group variance.

The held-out answers must come from images the routes do not contain (a gallery's test queries, for example:
`evaluate.py gallery.save=` writes them to queries.jsonl), answered with the same checkpoint, gallery and top-k as
the routes will be. The odometry noise (distance_sigma, heading_sigma_deg) is the odometry's, not the gallery's, and
is not fitted here.

q from single queries assumes that each frame's answer is new evidence. On a route it is not: frames a few metres
apart retrieve the same tiles, right and wrong alike, so a filter with that q trusts a run of frames too much and
its 95% region holds the truth less often than it says (docs/sequence.md measures it). fit_route_settings chooses
the filter's settings on held-out routes instead (routes the evaluation does not use, with their truth): of a grid
of settings (q, tile_sigma_m, ...), those whose 95% region holds the truth at the last frame on at least `level`
of the routes are calibrated, and of them the one with the smallest median region is chosen (ties: the one whose
last frame is more often within 25 m): the tightest region that is still honest. A larger q flattens each frame's
likelihood and a larger tile_sigma_m widens each answer: both widen the region. A setting whose region is the whole
gallery on most routes covers the truth trivially, and its area rules it out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from itertools import product

import numpy as np

from geoloc.sequence.measurement import FrameAnswer
from geoloc.sequence.particle_filter import FilterConfig
from geoloc.sequence.route_scores import RouteCase, RouteScores, score_routes

ROUTE_GRID = {"wrong_answer_prob": (0.3, 0.5, 0.7, 0.8, 0.9, 0.95)}  # what fit_route_settings tries by default


@dataclass(frozen=True)
class AnswerModel:
    """What fit_answer_model found: q and the temperature, with the counts they come from."""

    wrong_answer_prob: float
    temperature: float
    answers: int
    hits: int  # answers whose top-k holds a tile within radius_m of the truth
    right_scores: int  # scores of tiles within radius_m of their truth
    wrong_scores: int
    radius_m: float

    def applied(self, config: FilterConfig) -> FilterConfig:
        """config with the fitted q and temperature."""
        return replace(config, wrong_answer_prob=self.wrong_answer_prob, temperature=self.temperature)


def fit_answer_model(answers: Sequence[FrameAnswer], truths, radius_m: float = 25.0,
                     temperature: float | None = None) -> AnswerModel:
    """q and the temperature from held-out answers (FrameAnswer, centres in metres on the plane of `truths`) and
    their truths (N, 2) in the same metres. Empty slots (score -inf) are not tiles. q is kept inside
    [1 / (N + 2), 1 - 1 / (N + 2)] (the add-one estimate's range), since the filter needs 0 < q < 1.
    A given `temperature` (where the scores do not rank the tiles, say) is kept as it is and only q is fitted."""
    truths = np.asarray(truths, np.float64)
    if len(answers) == 0 or truths.shape != (len(answers), 2):
        raise ValueError(f"fitting needs one truth (east, north) per answer and at least one answer; got "
                         f"{len(answers)} answers and truths of shape {truths.shape}")
    if not radius_m > 0:
        raise ValueError(f"radius_m must be above 0, got {radius_m}")
    right, wrong, hits = [], [], 0
    for answer, truth in zip(answers, truths):
        live = np.isfinite(answer.scores)
        near = np.hypot(*(answer.centres - truth).T) <= radius_m
        right.append(answer.scores[live & near])
        wrong.append(answer.scores[live & ~near])
        hits += bool((live & near).any())
    right, wrong = np.concatenate(right), np.concatenate(wrong)
    n = len(answers)
    q = min(max(1.0 - hits / n, 1.0 / (n + 2)), 1.0 - 1.0 / (n + 2))
    if temperature is not None:
        if not temperature > 0:
            raise ValueError(f"a given temperature must be above 0, got {temperature}")
        return AnswerModel(q, float(temperature), n, hits, len(right), len(wrong), float(radius_m))
    if len(right) < 2 or len(wrong) < 2:
        raise ValueError(f"the held-out answers hold {len(right)} tiles within {radius_m} m of their truths and "
                         f"{len(wrong)} others; the temperature needs at least 2 of each: answer more held-out "
                         "images, or with a larger top-k")
    gap = right.mean() - wrong.mean()
    if not gap > 0:
        raise ValueError(f"near tiles score no higher than the others on average ({right.mean():.4f} against "
                         f"{wrong.mean():.4f}): the scores do not rank the tiles, so no temperature fits; weigh the "
                         "top-k equally instead (a large temperature, e.g. route.temperature=1.0)")
    pooled = (((right - right.mean()) ** 2).sum() + ((wrong - wrong.mean()) ** 2).sum()) / (len(right) + len(wrong) - 2)
    return AnswerModel(q, float(pooled / gap), n, hits, len(right), len(wrong), float(radius_m))


@dataclass(frozen=True)
class RouteFit:
    """What fit_route_settings found: the chosen settings (FilterConfig field -> value), whether their held-out
    coverage reached the level (False: no setting did, and the one covering most was chosen), and every setting's
    scores on the held-out routes, in the order tried."""

    settings: dict[str, float]
    calibrated: bool
    level: float
    scores: list[tuple[dict[str, float], RouteScores]] = field(default_factory=list)

    def applied(self, config: FilterConfig) -> FilterConfig:
        return replace(config, **self.settings)


def fit_route_settings(routes: Sequence[RouteCase], extent, config: FilterConfig,
                       grid: Mapping[str, Sequence[float]] = ROUTE_GRID, level: float = 0.95,
                       seed: int = 0) -> RouteFit:
    """Every combination of the `grid`'s values (FilterConfig fields, `config` for the rest) scored on the held-out
    `routes` over `extent` (route r with seed seed + r); of those whose `level` region holds the truth at the last
    frame on at least `level` of them, the one with the smallest median region (ties: the one more often within 25 m
    at the last frame); with calibrated False, the one covering most when none does."""
    known = {f.name: f.type for f in fields(FilterConfig)}
    if not grid or any(name not in known or len(values) == 0 for name, values in grid.items()):
        raise ValueError(f"the grid maps FilterConfig fields ({', '.join(sorted(known))}) to values to try; got "
                         f"{dict(grid)}")
    if not 0 < level < 1:
        raise ValueError(f"level must lie strictly between 0 and 1, got {level}")
    if len(routes) < 20:
        raise ValueError(f"{len(routes)} held-out routes cannot tell a {level:.0%} region's coverage from another: "
                         "fit on at least 20 (100 measure it to about 2 points)")
    names = list(grid)
    scores = []
    for values in product(*(grid[name] for name in names)):
        settings = {name: int(v) if known[name] in ("int", int) else float(v) for name, v in zip(names, values)}
        trial = replace(config, **settings)  # FilterConfig refuses a value out of its range, by name
        scores.append((settings, score_routes(routes, extent, trial, lambda r: seed + r, level=level)))
    calibrated = [(settings, s) for settings, s in scores if s.region >= level]
    if calibrated:
        best = min(calibrated, key=lambda item: (item[1].region_ha, -item[1].last))
    else:
        best = max(scores, key=lambda item: (item[1].region, -item[1].region_ha))
    return RouteFit(best[0], bool(calibrated), level, scores)
