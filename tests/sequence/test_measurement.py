"""A frame's answer as a Gaussian mixture (geoloc/sequence/measurement.py) against the formula written out."""

from __future__ import annotations

import numpy as np
import pytest

from geoloc.sequence.measurement import FrameAnswer, GaussianMixture, answer_mixture, tile_weights


def brute_density(answer: FrameAnswer, point, temperature, tile_sigma, refined_sigma) -> float:
    """sum_k w_k [c_k N(x; r_k, refined^2) + (1 - c_k) N(x; t_k, tile^2)], one term at a time."""
    e = [np.exp(s / temperature) for s in answer.scores]
    total = 0.0
    for k in range(len(answer)):
        w = e[k] / sum(e)
        c = 0.0 if answer.refined is None else answer.refined_confidence[k]

        def normal(mean, sigma):
            d2 = (point[0] - mean[0]) ** 2 + (point[1] - mean[1]) ** 2
            return np.exp(-d2 / (2 * sigma ** 2)) / (2 * np.pi * sigma ** 2)

        total += w * (1 - c) * normal(answer.centres[k], tile_sigma)
        if c > 0:
            total += w * c * normal(answer.refined[k], refined_sigma)
    return total


@pytest.mark.parametrize("refined", [False, True])
def test_mixture_density_is_the_formula(refined):
    rng = np.random.default_rng(0)
    centres, scores = rng.uniform(0, 200, (4, 2)), np.array([0.61, 0.58, 0.55, 0.40])
    answer = (FrameAnswer(centres, scores, centres + rng.normal(0, 10, (4, 2)), [1.0, 0.3, 0.0, 0.8]) if refined
              else FrameAnswer(centres, scores))
    mixture = answer_mixture(answer, 0.05, 25.0, 5.0)
    points = rng.uniform(-20, 220, (50, 2))
    expected = [brute_density(answer, p, 0.05, 25.0, 5.0) for p in points]
    np.testing.assert_allclose(mixture.density(points), expected, rtol=1e-10)
    assert mixture.weights.sum() == pytest.approx(1.0)


def test_refined_positions_without_confidence_count_as_right():
    answer = FrameAnswer([[0.0, 0.0]], [0.5], refined=[[10.0, 0.0]])
    mixture = answer_mixture(answer, 0.05, 25.0, 5.0)
    np.testing.assert_allclose(mixture.means, [[10.0, 0.0]])
    np.testing.assert_allclose(mixture.sigmas, [5.0])


def test_an_empty_slot_gets_no_weight():
    np.testing.assert_allclose(tile_weights([0.6, 0.6, -np.inf], 0.05), [0.5, 0.5, 0.0])


def test_mixture_samples_have_its_moments():
    mixture = GaussianMixture(np.array([[0.0, 0.0], [100.0, 50.0]]), np.array([5.0, 10.0]), np.array([0.25, 0.75]))
    draws = mixture.sample(200_000, np.random.default_rng(1))
    np.testing.assert_allclose(draws.mean(0), [75.0, 37.5], atol=0.3)
    assert np.mean(draws[:, 0] < 50) == pytest.approx(0.25, abs=0.005)


@pytest.mark.parametrize("kwargs, message", [
    (dict(centres=[[0, 0], [1, 1]], scores=[0.5]), "centres k x 2 and scores"),
    (dict(centres=[[0, 0]], scores=[np.nan]), "scores finite or -inf"),
    (dict(centres=[[0, 0]], scores=[-np.inf]), "at least one finite score"),
    (dict(centres=[[0, 0]], scores=[0.5], refined_confidence=[1.0]), "without refined positions"),
    (dict(centres=[[0, 0]], scores=[0.5], refined=[[1, 1]], refined_confidence=[1.5]), r"probabilities in \[0, 1\]"),
    (dict(centres=[[0, 0]], scores=[0.5], refined=[[np.nan, 1]], refined_confidence=[0.5]), "must be finite"),
])
def test_bad_answers_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FrameAnswer(**kwargs)


def test_a_dropped_refinement_may_be_missing():
    answer = FrameAnswer([[0.0, 0.0], [50.0, 0.0]], [0.5, 0.5], [[np.nan, np.nan], [52.0, 1.0]], [0.0, 1.0])
    assert len(answer_mixture(answer, 0.05, 25.0, 5.0).weights) == 2
