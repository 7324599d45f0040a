"""A frame's estimate (geoloc/sequence/estimate.py): the box density against a loop, the 95% region of one Gaussian
against its circle, of two modes against the ellipse, and with a uniform part that the samples cannot hold."""

from __future__ import annotations

import numpy as np
import pytest

from geoloc.sequence.cell_density import CellDensity
from geoloc.sequence.estimate import FrameEstimate
from geoloc.sequence.extent import GalleryExtent

EXTENT = GalleryExtent(0.0, 1000.0, 0.0, 1000.0)


def estimate_of(points, tracked_mass=1.0, headings=None) -> FrameEstimate:
    samples = np.column_stack([points, np.zeros(len(points)) if headings is None else headings])
    return FrameEstimate.from_samples(samples, np.full(len(points), 1 / len(points)), tracked_mass, EXTENT, 5.0, 40.0)


def test_cell_density_is_the_block_weight_over_its_area():
    rng = np.random.default_rng(0)
    points, weights = rng.normal(50, 8, (300, 2)), rng.random(300)
    weights /= weights.sum()
    density = CellDensity(points, weights, 5.0)
    queries = np.concatenate([rng.normal(50, 12, (40, 2)), points[:10]])
    expected = []
    for q in queries:
        ci, cj = np.floor(q / 5.0)
        inside = (np.abs(np.floor(points[:, 0] / 5.0) - ci) <= 1) & (np.abs(np.floor(points[:, 1] / 5.0) - cj) <= 1)
        expected.append(weights[inside].sum() / (9 * 25.0))
    np.testing.assert_allclose(density.at(queries), expected)
    np.testing.assert_allclose(density.at_own_points(), density.at(points))


def test_one_gaussian_region_is_its_circle():
    rng = np.random.default_rng(1)
    sigma, centre = 20.0, np.array([500.0, 500.0])
    estimate = estimate_of(centre + sigma * rng.standard_normal((40_000, 2)))
    # the 95% circle has radius sqrt(5.991) sigma = 2.45 sigma
    for radius, inside in ((2.2, True), (2.75, False)):
        for angle in np.radians([0, 60, 135, 250]):
            point = centre + radius * sigma * np.array([np.cos(angle), np.sin(angle)])
            assert estimate.contains(point) is inside
            assert estimate.in_ellipse(point) is inside
    assert estimate.region_area_m2() == pytest.approx(np.pi * 5.991 * sigma ** 2, rel=0.1)
    assert estimate.ellipse_area_m2() == pytest.approx(np.pi * 5.991 * sigma ** 2, rel=0.03)
    np.testing.assert_allclose(estimate.position, centre, atol=0.5)


def test_two_modes_leave_the_space_between_them_out():
    rng = np.random.default_rng(2)
    west, east = rng.normal([300.0, 500.0], 10.0, (20_000, 2)), rng.normal([600.0, 500.0], 10.0, (10_000, 2))
    headings = np.concatenate([np.full(20_000, 350.0), np.full(10_000, 90.0)])
    estimate = estimate_of(np.concatenate([west, east]), headings=headings)
    between = np.array([450.0, 500.0])
    assert estimate.in_ellipse(between) and not estimate.contains(between)
    assert estimate.contains([300.0, 500.0]) and estimate.contains([600.0, 500.0])
    assert estimate.region_area_m2() < 0.2 * estimate.ellipse_area_m2()  # two discs of 95%: about 3,800 m²
    # the point estimate is the heavier mode, not the mean between them
    np.testing.assert_allclose(estimate.position, [300.0, 500.0], atol=1.0)
    assert estimate.heading_deg == pytest.approx(350.0)


def test_a_heavy_uniform_part_makes_the_region_the_whole_gallery():
    points = np.random.default_rng(3).normal(500.0, 10.0, (5000, 2))
    estimate = estimate_of(points, tracked_mass=0.9)
    assert estimate.whole_gallery()
    assert estimate.contains([10.0, 990.0]) and not estimate.contains([-10.0, 500.0])
    assert estimate.region_area_m2() == EXTENT.area_m2
    # at 80% the samples' 90% is enough: the region is theirs
    assert not estimate.whole_gallery(0.8) and not estimate.contains([10.0, 990.0], 0.8)

