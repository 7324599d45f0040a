"""The filter's answer model fitted from held-out single-image answers whose positions are known.

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
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from geoloc.sequence.measurement import FrameAnswer
from geoloc.sequence.particle_filter import FilterConfig


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


def fit_answer_model(answers: Sequence[FrameAnswer], truths, radius_m: float = 25.0) -> AnswerModel:
    """q and the temperature from held-out answers (FrameAnswer, centres in metres on the plane of `truths`) and
    their truths (N, 2) in the same metres. Empty slots (score -inf) are not tiles. q is kept inside
    [1 / (N + 2), 1 - 1 / (N + 2)] (the add-one estimate's range), since the filter needs 0 < q < 1."""
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
    q = min(max(1.0 - hits / n, 1.0 / (n + 2)), 1.0 - 1.0 / (n + 2))
    return AnswerModel(q, float(pooled / gap), n, hits, len(right), len(wrong), float(radius_m))
