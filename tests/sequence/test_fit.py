"""The answer model fitted from held-out answers (geoloc/sequence/fit.py): against the formula on hand-made answers,
and recovering a simulation's known hit rate and temperature."""

from __future__ import annotations

import numpy as np
import pytest

from geoloc.sequence.fit import fit_answer_model
from geoloc.sequence.measurement import FrameAnswer
from geoloc.sequence.particle_filter import FilterConfig
from geoloc.sequence.simulation import SimulatedGallery, SimulationConfig


def test_q_and_temperature_are_the_formula():
    truths = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 500.0]])
    answers = [
        FrameAnswer([[10.0, 0.0], [300.0, 0.0], [0.0, 90.0]], [0.9, 0.5, 0.4]),  # one near (10 m)
        FrameAnswer([[100.0, 24.0], [100.0, 26.0], [0.0, 0.0]], [0.8, 0.7, -np.inf]),  # 24 m near, 26 m not, empty
        FrameAnswer([[0.0, 0.0], [50.0, 50.0], [9.0, 9.0]], [0.6, 0.3, 0.2]),  # nothing near its truth
    ]
    model = fit_answer_model(answers, truths, radius_m=25.0)
    right = np.array([0.9, 0.8])
    wrong = np.array([0.5, 0.4, 0.7, 0.6, 0.3, 0.2])
    pooled = (((right - right.mean()) ** 2).sum() + ((wrong - wrong.mean()) ** 2).sum()) / (2 + 6 - 2)
    assert model.hits == 2 and model.answers == 3
    assert (model.right_scores, model.wrong_scores) == (2, 6)
    assert model.wrong_answer_prob == pytest.approx(1 / 3)
    assert model.temperature == pytest.approx(pooled / (right.mean() - wrong.mean()))
    applied = model.applied(FilterConfig(heading_sigma_deg=2.0))
    assert (applied.wrong_answer_prob, applied.temperature, applied.heading_sigma_deg) == (
        model.wrong_answer_prob, model.temperature, 2.0)


def test_q_stays_inside_the_open_interval():
    truths = np.zeros((4, 2))
    near = [FrameAnswer([[0.0, 0.0], [500.0, 0.0], [0.0, 600.0]], [0.9 - i / 100, 0.5, 0.4 + i / 100]) for i in range(4)]
    assert fit_answer_model(near, truths).wrong_answer_prob == pytest.approx(1 / 6)  # every answer a hit
    # the truths moved away: no answer has a near tile, so no temperature can be fitted
    with pytest.raises(ValueError, match="at least 2 of each"):
        fit_answer_model(near, truths + 1000.0)


def test_scores_that_do_not_rank_the_tiles_are_refused():
    truths = np.zeros((2, 2))
    answers = [FrameAnswer([[0.0, 0.0], [500.0, 0.0]], [0.3, 0.9]), FrameAnswer([[0.0, 0.0], [500.0, 0.0]], [0.2, 0.8])]
    with pytest.raises(ValueError, match="do not rank the tiles"):
        fit_answer_model(answers, truths)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="one truth"):
        fit_answer_model([FrameAnswer([[0.0, 0.0]], [1.0])], np.zeros((2, 2)))


def test_recovers_a_simulated_hit_rate_and_temperature():
    """Answers drawn as the simulation draws a route's frames: the right tile (one of the four holding the camera)
    with probability hit_prob. With the radius covering those four (a half-tile lattice step on each axis), the fit
    finds q = 1 - hit_prob, less the few random tiles that fall near by chance, and the matched temperature."""
    config = SimulationConfig(hit_prob=0.3)
    gallery = SimulatedGallery(config)
    rng = np.random.default_rng(0)
    truths = rng.uniform(200.0, 1800.0, (3000, 2))
    answers = [gallery.answer(t, rng.random() < config.hit_prob, rng) for t in truths]
    radius = np.hypot(config.tile_width_m / 2, config.tile_width_m / 2)
    model = fit_answer_model(answers, truths, radius)
    assert model.wrong_answer_prob == pytest.approx(1 - config.hit_prob, abs=0.03)
    assert model.temperature == pytest.approx(config.matched_temperature, rel=0.15)


def test_a_given_temperature_is_kept_and_only_q_is_fitted():
    truths = np.zeros((3, 2))
    flat = [FrameAnswer([[0.0, 0.0], [500.0, 0.0]], [0.5, 0.5]), FrameAnswer([[400.0, 0.0], [500.0, 0.0]], [0.5, 0.5]),
            FrameAnswer([[10.0, 0.0], [500.0, 0.0]], [0.5, 0.5])]
    with pytest.raises(ValueError, match="do not rank the tiles"):
        fit_answer_model(flat, truths)
    model = fit_answer_model(flat, truths, temperature=1.0)
    assert model.temperature == 1.0 and model.hits == 2 and model.wrong_answer_prob == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="above 0"):
        fit_answer_model(flat, truths, temperature=0.0)
