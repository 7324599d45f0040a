"""The sequence filter (geoloc/sequence/particle_filter.py) against a brute-force Bayes posterior, in simulation
(better than single frames, an honest 95% region, a wrong frame absorbed), and its determinism."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from geoloc.sequence import (FilterConfig, FrameAnswer, GalleryExtent, Odometry, SimulatedGallery, SimulationConfig,
                             localize_route)
from geoloc.sequence.measurement import answer_mixture
from geoloc.sequence.particle_filter import fused_frames, systematic_resample

# --- against brute force ----------------------------------------------------------------------------------------

EXTENT = GalleryExtent(0.0, 300.0, 0.0, 300.0)
EXACT = FilterConfig(particles=20000, ring_samples=20000, tile_sigma_m=15.0, temperature=0.05,
                     wrong_answer_prob=0.6, distance_sigma=0.0, heading_sigma_deg=0.0, position_jitter_m=0.0)
# three frames: turn 90 degrees and go 20 m, turn -45 degrees and go 25 m. Each answer has a tile near the truth
# (120, 150) -> (140, 150) -> (157.7, 167.7), one near the same route turned round from (230, 80), and decoys: the
# posterior has two modes, and its mean depends on how the filter weighs them
ODOMETRY = Odometry(np.array([0.0, 20.0, 25.0]), np.array([0.0, 90.0, -45.0]))
ANSWERS = [
    FrameAnswer([[125.0, 145.0], [232.0, 78.0], [80.0, 220.0]], [0.60, 0.58, 0.52]),
    FrameAnswer([[145.0, 152.0], [208.0, 83.0]], [0.58, 0.58]),
    FrameAnswer([[158.0, 170.0], [190.0, 65.0], [90.0, 100.0]], [0.60, 0.57, 0.52]),
]
TRUTH_LAST = np.array([140.0 + 25.0 / math.sqrt(2), 150.0 + 25.0 / math.sqrt(2)])


def brute_force_posterior(cell_m: float = 2.0, heading_bins: int = 360):
    """The exact posterior over the last frame, by enumerating every start (a grid over the extent) and first
    heading (a grid over the circle) and carrying each along the noiseless odometry: for every state the product of
    the frames' likelihoods q/A + (1-q) M_t(x_t). Returns (the uniform part's probability (q/A)^T / Z, the mean of
    the last position and of (sin, cos) of the last heading under the rest of the posterior, and the share of that
    rest within 40 m of the truth's last position)."""
    q, area = EXACT.wrong_answer_prob, EXTENT.area_m2
    mixtures = [answer_mixture(a, EXACT.temperature, EXACT.tile_sigma_m, EXACT.refined_sigma_m) for a in ANSWERS]
    axis = np.arange(cell_m / 2, 300.0, cell_m)
    start = np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    floor = (q / area) ** len(ANSWERS)
    total = weight_sum = 0.0
    moments = np.zeros(5)  # east, north, sin, cos of the last heading, near the truth; weighted by (product - floor)
    for first in np.arange(heading_bins) * 2 * np.pi / heading_bins:
        x, heading, product = start.copy(), first, np.ones(len(start))
        for frame, mixture in enumerate(mixtures):
            if frame:
                heading += math.radians(ODOMETRY.heading_change_deg[frame])
                x = x + ODOMETRY.distance_m[frame] * np.array([math.sin(heading), math.cos(heading)])
            product *= q / area + (1 - q) * mixture.density(x)
        rest = product - floor
        total += product.sum()
        weight_sum += rest.sum()
        near = np.hypot(*(x - TRUTH_LAST).T) < 40.0
        moments += [rest @ x[:, 0], rest @ x[:, 1], rest.sum() * math.sin(heading), rest.sum() * math.cos(heading),
                    rest[near].sum()]
    states = len(start) * heading_bins
    return floor / (total / states), moments / weight_sum


def test_filter_matches_the_brute_force_posterior():
    uniform_exact, (east, north, sin_h, cos_h, near_truth) = brute_force_posterior()
    last = localize_route(ANSWERS, ODOMETRY, EXTENT, EXACT, seed=0)[-1]
    heading = np.radians(last.samples[:, 2])
    sin_cos = (last.weights @ np.sin(heading), last.weights @ np.cos(heading))
    near = last.weights[np.hypot(*(last.samples[:, :2] - TRUTH_LAST).T) < 40.0].sum()
    print(f"uniform part: filter {1 - last.tracked_mass:.4f}, exact {uniform_exact:.4f}; last position: filter "
          f"{last.mean.round(2)}, exact {np.round([east, north], 2)}; heading (sin, cos): filter "
          f"{np.round(sin_cos, 3)}, exact {np.round([sin_h, cos_h], 3)}; within 40 m of the truth: filter "
          f"{near:.3f}, exact {near_truth:.3f}")
    assert 1 - last.tracked_mass == pytest.approx(uniform_exact, rel=0.03)
    # Monte Carlo error with 20,000 particles: the two modes lie 100 m apart, so the mean's standard error is about
    # 0.5 m and a share's about 0.005
    assert last.mean == pytest.approx([east, north], abs=1.5)
    assert near == pytest.approx(near_truth, abs=0.02)
    assert sin_cos == pytest.approx([sin_h, cos_h], abs=0.03)


# --- in simulation ----------------------------------------------------------------------------------------------

ROUTES = 300
HIT_PROB = 0.3
# the 95% region's coverage over ROUTES independent routes is binomial: standard deviation
# sqrt(0.95 * 0.05 / 300) = 1.26 points, so a calibrated region lands within 3 of them (3.8 points) for 99.7% of
# seeds
COVERAGE_TOLERANCE = 3 * math.sqrt(0.95 * 0.05 / ROUTES)


def matched_config(simulation: SimulationConfig, **changes) -> FilterConfig:
    """The filter's defaults with the simulation's wrong-answer rate, score temperature and odometry noise."""
    matched = dict(wrong_answer_prob=1 - simulation.hit_prob, temperature=simulation.matched_temperature,
                   distance_sigma=simulation.distance_noise, heading_sigma_deg=simulation.heading_noise_deg)
    return FilterConfig(**{**matched, **changes})


@pytest.fixture(scope="module")
def simulated():
    """ROUTES routes of 20 frames at HIT_PROB: per route, the single answers' top-1 errors (F,) and the last frame's
    truth and estimate."""
    simulation = SimulationConfig(hit_prob=HIT_PROB)
    gallery = SimulatedGallery(simulation)
    config = matched_config(simulation)
    rng = np.random.default_rng(2024)
    out = []
    for seed in range(ROUTES):
        route = gallery.route(rng)
        last = localize_route(route.answers, route.odometry, gallery.extent, config, seed=seed)[-1]
        top1 = np.array([np.hypot(*(a.centres[0] - x)) for a, x in zip(route.answers, route.truth)])
        out.append((top1, route.truth[-1], last))
    return out


@pytest.mark.slow
def test_the_route_localises_far_more_often_than_single_frames(simulated):
    single = np.mean([top1 <= 25.0 for top1, _, _ in simulated])
    last = np.mean([np.hypot(*(e.position - x)) <= 25.0 for _, x, e in simulated])
    print(f"within 25 m: single frames {single:.3f}, the route's last frame {last:.3f} ({last / single:.1f}x)")
    assert last >= 2 * single


@pytest.mark.slow
def test_the_95_percent_region_holds_the_truth_95_percent_of_the_time(simulated):
    region = np.mean([e.contains(x) for _, x, e in simulated])
    ellipse = np.mean([e.in_ellipse(x) for _, x, e in simulated])
    whole = np.mean([e.whole_gallery() for _, _, e in simulated])
    print(f"95% region holds the truth: highest density {region:.3f}, Gaussian ellipse {ellipse:.3f} "
          f"(tolerance {COVERAGE_TOLERANCE:.3f}); regions that are the whole gallery {whole:.3f}")
    assert abs(region - 0.95) <= COVERAGE_TOLERANCE


def far_answer(gallery: SimulatedGallery, truth, k: int = 5) -> FrameAnswer:
    """k tiles about a kilometre from the truth, scored higher than any right tile would be."""
    away = np.asarray(truth) + [800.0, -600.0] if truth[1] > 1000 else np.asarray(truth) + [-600.0, 800.0]
    rows = np.argsort(np.hypot(*(gallery.centres - away).T))[:k]
    return FrameAnswer(gallery.centres[rows], np.linspace(0.75, 0.70, k))


@pytest.mark.parametrize("seed", range(4))
def test_one_wildly_wrong_frame_does_not_pull_the_route_away(seed):
    """Every frame right but frame 10, whose top-k lie a kilometre off: from frame 10 on, the estimates stay within
    10 m of those of the same route with frame 10 right (losing one right answer moves them a few metres; following
    the wrong one would move them a kilometre), and within 30 m of the truth."""
    simulation = SimulationConfig(hit_prob=1.0)
    gallery = SimulatedGallery(simulation)
    route = gallery.route(np.random.default_rng(seed))
    answers = list(route.answers)
    answers[10] = far_answer(gallery, route.truth[10])
    config = matched_config(simulation, wrong_answer_prob=0.5)  # the filter still expects wrong answers
    clean, pulled = (localize_route(a, route.odometry, gallery.extent, config, seed=seed)
                     for a in (route.answers, answers))
    moved = np.array([np.hypot(*(a.position - b.position)) for a, b in zip(clean, pulled)])
    errors = np.array([np.hypot(*(e.position - x)) for e, x in zip(pulled, route.truth)])
    print(f"from frame 8 on: errors (m) {errors[8:].round(1)}, moved by the wrong frame (m) {moved[8:].round(1)}; "
          f"its top-1 is {np.hypot(*(answers[10].centres[0] - route.truth[10])):.0f} m off")
    assert (moved[10:] <= 10.0).all()
    assert (errors[10:] <= 30.0).all()


@pytest.mark.parametrize("seed", range(4))
def test_a_wrong_first_frame_is_recovered_from(seed):
    simulation = SimulationConfig(hit_prob=1.0)
    gallery = SimulatedGallery(simulation)
    route = gallery.route(np.random.default_rng(seed))
    answers = [far_answer(gallery, route.truth[0]), *route.answers[1:]]
    config = matched_config(simulation, wrong_answer_prob=0.5)
    last = localize_route(answers, route.odometry, gallery.extent, config, seed=seed)[-1]
    assert np.hypot(*(last.position - route.truth[-1])) <= 25.0


# --- resampling and determinism -------------------------------------------------------------------------------


def test_systematic_resampling_copies_each_particle_its_share():
    weights = np.array([0.5, 0.3, 0.15, 0.05])
    counts = np.bincount(systematic_resample(weights, 20, np.random.default_rng(4)), minlength=4)
    assert counts.sum() == 20
    assert (counts >= np.floor(20 * weights)).all() and (counts <= np.ceil(20 * weights)).all()


def test_the_same_seed_gives_the_same_estimates():
    simulation = SimulationConfig(hit_prob=0.5, frames=8)
    gallery = SimulatedGallery(simulation)
    route = gallery.route(np.random.default_rng(3))
    config = matched_config(simulation, particles=500, ring_samples=200)
    first, again, other = (localize_route(route.answers, route.odometry, gallery.extent, config, seed=s)
                           for s in (7, 7, 8))
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.samples, b.samples)
        np.testing.assert_array_equal(a.position, b.position)
        assert a.heading_deg == b.heading_deg and a.tracked_mass == b.tracked_mass
    assert not np.array_equal(first[-1].samples, other[-1].samples)


def test_a_route_needs_one_answer_per_odometry_row():
    gallery = SimulatedGallery(SimulationConfig(frames=4))
    route = gallery.route(np.random.default_rng(0))
    with pytest.raises(ValueError, match="3 frame answers but 4 odometry rows"):
        localize_route(route.answers[:3], route.odometry, gallery.extent)


# --- fusing every so many metres ----------------------------------------------------------------------------------


def test_frames_are_fused_once_the_odometry_has_gone_far_enough():
    odometry = Odometry(np.array([0.0, 10.0, 10.0, 4.0, 12.0, 30.0, 1.0]), np.zeros(7))
    assert fused_frames(odometry, 0.0) == list(range(7))
    assert fused_frames(odometry, 20.0) == [0, 2, 5]  # 20 m; then 4 + 12 = 16, short; + 30
    assert fused_frames(odometry, 25.0) == [0, 4, 5]  # 10 + 10 + 4 + 12 = 36; 30
    assert fused_frames(odometry, 1000.0) == [0]


def test_an_unfused_frame_changes_nothing():
    """With fuse_every_m 25 and frames 10 m apart, frames 1, 2, 4, 5, ... are not weighed: giving them a wildly wrong
    answer leaves every estimate as it was (the same seed), whereas with every frame fused it moves them."""
    simulation = SimulationConfig(hit_prob=1.0, frames=8)
    gallery = SimulatedGallery(simulation)
    route = gallery.route(np.random.default_rng(1))
    skipped = [i for i in range(8) if i not in fused_frames(route.odometry, 25.0)]
    assert skipped == [1, 2, 4, 5, 7]
    wrong = [far_answer(gallery, route.truth[i]) if i in skipped else a for i, a in enumerate(route.answers)]
    sparse = matched_config(simulation, particles=500, ring_samples=200, fuse_every_m=25.0, wrong_answer_prob=0.5)
    for a, b in zip(*(localize_route(ans, route.odometry, gallery.extent, sparse, seed=3) for ans in (route.answers, wrong))):
        np.testing.assert_array_equal(a.samples, b.samples)
    every = replace(sparse, fuse_every_m=0.0)
    clean, pulled = (localize_route(ans, route.odometry, gallery.extent, every, seed=3) for ans in (route.answers, wrong))
    assert not np.array_equal(clean[1].samples, pulled[1].samples)


def test_fuse_every_m_must_be_a_distance():
    with pytest.raises(ValueError, match="fuse_every_m is a distance"):
        FilterConfig(fuse_every_m=-1.0)
