"""The one-answer hypotheses (geoloc/sequence/rings.py): their pair masses against a dense integral over the birth
heading, their transport against the route walked step by step, and their odometry variance against its sum."""

from __future__ import annotations

import math

import numpy as np
import pytest

from geoloc.sequence.measurement import GaussianMixture
from geoloc.sequence.rings import Rings

STEPS = [(10.0, 0.0), (12.0, 90.0), (8.0, -30.0), (15.0, 45.0)]  # (distance, turn) after birth


def rings_after(steps, means=((100.0, 100.0),), sigma=20.0) -> Rings:
    rings = Rings()
    rings.add(GaussianMixture(np.array(means, float), np.full(len(means), sigma), np.full(len(means), 1 / len(means))),
              1.0)
    for distance, turn in steps:
        rings.move(distance, turn)
    return rings


def test_transport_is_the_route_walked_from_each_birth_heading():
    rings = rings_after(STEPS)
    for birth in np.radians([0.0, 37.0, 200.0]):
        x, heading = np.array([100.0, 100.0]), birth
        for distance, turn in STEPS:
            heading += math.radians(turn)
            x = x + distance * np.array([math.sin(heading), math.cos(heading)])
        np.testing.assert_allclose(rings.ring_points(np.array([0]), np.array([birth]))[0], x, atol=1e-9)
    assert rings.turned[0] == pytest.approx(sum(t for _, t in STEPS))


def test_odometry_variance_is_its_sum_over_turns():
    rings = rings_after(STEPS)
    distances = np.array([d for d, _ in STEPS])
    # a heading error at turn r is carried over the distance walked from r on, that turn's own step included
    levers = np.cumsum(distances[::-1])[::-1]
    sigma_d, sigma_h, jitter = 0.05, 2.0, 0.5
    expected = (20.0 ** 2 + 0.5 * sigma_d ** 2 * (distances ** 2).sum()
                + 0.5 * math.radians(sigma_h) ** 2 * (levers ** 2).sum() + len(STEPS) * jitter ** 2)
    assert rings.variance(sigma_d, sigma_h, jitter)[0] == pytest.approx(expected)


@pytest.mark.parametrize("steps, answer", [
    (STEPS, (130.0, 120.0)),  # the answer on the ring
    (STEPS, (100.0, 100.0)),  # inside it
    ([], (110.0, 95.0)),  # a ring of radius 0: two Gaussians at one frame
    ([(150.0, 0.0)], (100.0, 248.0)),  # a wide ring: the arc is a sliver of the circle
])
def test_pair_mass_is_the_integral_over_birth_headings(steps, answer):
    rings = rings_after(steps, means=((100.0, 100.0), (900.0, 900.0)))
    variance = rings.variance(0.05, 1.0, 0.5)
    mixture = GaussianMixture(np.array([answer]), np.array([10.0]), np.array([1.0]))
    h, b, theta, density, step = rings.pair_arcs(variance, mixture)
    assert list(h) == [0]  # the far ring cannot reach the answer
    mass = density.sum(1) * step / (2 * np.pi)
    birth = np.linspace(0.0, 2 * np.pi, 200_000, endpoint=False)
    points = rings.ring_points(np.zeros(len(birth), int), birth)
    var = variance[0] + 10.0 ** 2
    exact = np.mean(np.exp(-0.5 * ((points - answer) ** 2).sum(1) / var) / (2 * np.pi * var))
    assert mass[0] == pytest.approx(exact, rel=1e-3)
