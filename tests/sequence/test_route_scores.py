"""The route figures (geoloc/sequence/route_scores.py) on hand-made routes whose answers are known, and q chosen on
held-out routes (fit.py's fit_route_settings)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from geoloc.sequence.extent import GalleryExtent
from geoloc.sequence.fit import fit_route_settings
from geoloc.sequence.measurement import FrameAnswer
from geoloc.sequence.odometry import Odometry
from geoloc.sequence.particle_filter import FilterConfig
from geoloc.sequence.route_scores import RouteCase, score_routes
from geoloc.sequence.simulation import SimulatedGallery, SimulationConfig

EXTENT = GalleryExtent(-1000.0, 1000.0, -1000.0, 1000.0)
CONFIG = FilterConfig(particles=1000, wrong_answer_prob=0.2, temperature=0.05)


def straight_route(start, frames: int, answer_at, single=None) -> RouteCase:
    """A route driving north 10 m a frame from `start`; answer_at(truth) gives each frame's FrameAnswer."""
    truth = np.asarray(start, float) + np.column_stack([np.zeros(frames), 10.0 * np.arange(frames)])
    odometry = Odometry(np.array([0.0] + [10.0] * (frames - 1)), np.zeros(frames))
    return RouteCase([answer_at(t) for t in truth], odometry, truth, single)


def test_right_answers_are_found_and_wrong_ones_are_not():
    right = straight_route([0.0, 0.0], 8, lambda t: FrameAnswer([t + [3.0, 0.0], [700.0, 700.0]], [0.9, 0.5]))
    # every frame's top-1 800 m away, the second tile near the truth but scored far lower
    wrong = straight_route([-500.0, -500.0], 8, lambda t: FrameAnswer([[300.0, 300.0], t], [0.9, 0.1]))
    s = score_routes([right, wrong], EXTENT, CONFIG)
    assert s.routes == 2 and s.single == pytest.approx(0.5)  # 8 of 16 frames' top-1 within 25 m
    assert s.last == pytest.approx(0.5) and s.ratio == pytest.approx(1.0)
    assert s.region >= 0.5 and s.ellipse >= 0.5  # the right route's region holds its truth
    # only the wrong route has a frame more than 50 m off, first frame included, and it is not found
    assert s.recover == 0.0 and s.first_wrong == 0.0
    assert s.region_ha > 0 and s.ellipse_ha > 0 and s.ms_per_frame > 0


def test_the_own_answers_count_where_given_and_nan_where_no_route_qualifies():
    right = straight_route([0.0, 0.0], 5, lambda t: FrameAnswer([t, [700.0, 700.0]], [0.9, 0.5]))
    assert math.isnan(score_routes([right], EXTENT, CONFIG).recover)  # no frame ever 50 m off
    # the same answers, but the frames' own answers (a refiner's, say) 30 m off on frames 0 and 3
    own = right.truth + np.array([[30.0, 0.0], [0, 0], [0, 0], [0, 30.0], [0, 0]])
    s = score_routes([replace(right, single=own)], EXTENT, CONFIG)
    assert s.single == pytest.approx(3 / 5) and s.last == 1.0
    assert math.isnan(s.recover) and math.isnan(s.first_wrong)  # 30 m is not more than 50 m off
    far = right.truth + np.array([[60.0, 0.0], [0, 0], [0, 0], [0, 0], [0, 0]])
    s = score_routes([replace(right, single=far)], EXTENT, CONFIG)
    assert (s.recover, s.first_wrong) == (1.0, 1.0)
    with pytest.raises(ValueError, match="at least one route"):
        score_routes([], EXTENT, CONFIG)


def simulated_routes(count: int, seed: int, hit_prob: float) -> tuple[list[RouteCase], object]:
    gallery = SimulatedGallery(SimulationConfig(hit_prob=hit_prob))
    rng = np.random.default_rng(seed)
    routes = [gallery.route(rng) for _ in range(count)]
    return [RouteCase(r.answers, r.odometry, r.truth) for r in routes], gallery.extent


def test_the_settings_are_chosen_on_held_out_routes_calibrated_first_then_the_tightest():
    cases, extent = simulated_routes(40, seed=0, hit_prob=0.5)
    config = FilterConfig(particles=1000, temperature=SimulationConfig().matched_temperature)
    grid = {"wrong_answer_prob": [0.5, 0.9], "tile_sigma_m": [25.0, 35.0]}
    fit = fit_route_settings(cases, extent, config, grid)
    assert [settings for settings, _ in fit.scores] == [
        {"wrong_answer_prob": q, "tile_sigma_m": t} for q in (0.5, 0.9) for t in (25.0, 35.0)]
    calibrated = [(settings, s) for settings, s in fit.scores if s.region >= 0.95]
    assert fit.calibrated and len(calibrated) < len(fit.scores)  # some settings under-cover, some do not
    chosen = next(s for settings, s in fit.scores if settings == fit.settings)
    assert chosen.region >= 0.95 and chosen.region_ha == min(s.region_ha for _, s in calibrated)
    # each setting's figures are score_routes' with it and seed r for route r
    settings, first = fit.scores[0]
    again = score_routes(cases, extent, replace(config, **settings), lambda r: r)
    assert again == replace(first, ms_per_frame=again.ms_per_frame)
    assert fit.applied(config) == replace(config, **fit.settings)


def test_a_route_fit_says_when_nothing_is_calibrated_and_refuses_what_cannot_be_fitted():
    cases, extent = simulated_routes(20, seed=1, hit_prob=0.05)
    fit = fit_route_settings(cases, extent, FilterConfig(particles=500, temperature=0.05),
                             {"wrong_answer_prob": [0.01, 0.02]})
    assert not fit.calibrated  # told every answer is right when 95% are wrong: the region misses
    assert fit.settings["wrong_answer_prob"] == max(fit.scores, key=lambda item: item[1].region)[0]["wrong_answer_prob"]
    assert isinstance(fit_route_settings(cases, extent, FilterConfig(particles=200), {"particles": [100]},
                                         ).settings["particles"], int)
    with pytest.raises(ValueError, match="at least 20"):
        fit_route_settings(cases[:19], extent, CONFIG)
    with pytest.raises(ValueError, match="FilterConfig fields"):
        fit_route_settings(cases, extent, CONFIG, {"wrong_answer": [0.5]})
    with pytest.raises(ValueError, match="wrong_answer_prob is a probability"):
        fit_route_settings(cases, extent, CONFIG, {"wrong_answer_prob": [0.5, 1.0]})
    with pytest.raises(ValueError, match="level"):
        fit_route_settings(cases, extent, CONFIG, level=1.0)
