"""The 360° canvas of a limited-FoV street view (geoloc/tasks/crossview/views.py) against per-column brute force."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from geoloc.config import ConfigError
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.heading import query_candidates
from geoloc.tasks.crossview.transforms import align_query, image_tensor, to_tensor
from geoloc.tasks.crossview.views import (
    circular_error_deg,
    crop_view,
    north_window,
    view_canvas,
)


def bearing_panorama(width: int, height: int = 3) -> np.ndarray:
    """A panorama whose pixel values name their column (column + 1, so 0 stays 'empty')."""
    cols = np.arange(width, dtype=np.int32) + 1
    return np.broadcast_to(cols[None, :, None], (height, width, 2)).copy()


def brute_canvas(street: np.ndarray, fov: float, heading: float, width: int) -> np.ndarray:
    """Canvas column c looks along 180 + 360c/W; view column i along h - f/2 + f·i/W'. Put each view column on
    the canvas column of the same bearing (bearings chosen so they meet exactly)."""
    canvas = np.zeros((street.shape[0], width, *street.shape[2:]), street.dtype)
    for c in range(width):
        canvas_bearing = (180.0 + 360.0 * c / width) % 360.0
        for i in range(street.shape[1]):
            view_bearing = (heading - fov / 2 + fov * i / street.shape[1]) % 360.0
            if abs(canvas_bearing - view_bearing) < 1e-9:
                canvas[:, c] = street[:, i]
    return canvas


@pytest.mark.parametrize("fov,view_width,heading", [
    (90, 90, 0), (90, 90, 37), (180, 180, 271), (70, 70, 359), (360, 360, 123), (90, 180, 12.5), (70, 140, 200.5)])
def test_canvas_matches_a_per_column_brute_force(fov, view_width, heading):
    rng = np.random.default_rng(0)
    street = rng.integers(1, 255, (4, view_width, 3), dtype=np.uint8)
    canvas = view_canvas(street, fov, heading)
    width = round(view_width * 360 / fov)
    assert canvas.shape == (4, width, 3)
    assert np.array_equal(canvas, brute_canvas(street, fov, heading, width))


def test_the_canvas_is_the_view_scattered_to_its_columns():
    """view_canvas copies the view as one wrapping run of columns: the same canvas as scattering each view column to
    the canvas column _view_columns gives it, for widths whose ratio is not whole and headings anywhere."""
    from geoloc.tasks.crossview.views import _view_columns, canvas_columns

    rng = np.random.default_rng(5)
    for _ in range(200):
        view_width, fov, heading = int(rng.integers(1, 90)), float(rng.uniform(1, 360)), float(rng.uniform(-720, 720))
        street = rng.integers(1, 255, (2, view_width, 3), dtype=np.uint8)
        width = round(canvas_columns(view_width, fov))
        scattered = np.zeros((2, width, 3), np.uint8)
        scattered[:, _view_columns(width, view_width, fov, heading)] = street
        assert np.array_equal(view_canvas(street, fov, heading), scattered), (view_width, fov, heading)


@pytest.mark.parametrize("alignment", ["ipt", "ground", "polar", "none"])
def test_the_candidate_inputs_are_each_headings_canvas_aligned(alignment):
    """query_inputs reads each heading's canvas as a window of one doubled canvas: bit for bit the inputs of
    aligning view_canvas(street, fov, h) one heading at a time (the definition)."""
    from geoloc.tasks.crossview.heading import query_inputs

    cfg = CrossViewDataConfig(alignment=alignment, aerial_size=32, pano_size=[16, 64])
    rng = np.random.default_rng(7)
    for view_width, fov in ((96, 360.0), (37, 90.0), (50, 127.3), (1, 360.0), (3, 1.5)):
        street = rng.integers(0, 255, (20, view_width, 3), dtype=np.uint8)
        headings = np.concatenate([rng.uniform(-400, 400, 6), [0.0, 359.99]])
        expect = torch.stack([to_tensor(align_query(view_canvas(street, fov, h), cfg)) for h in headings])
        assert torch.equal(query_inputs(street, cfg, "panorama", fov, headings), expect), (view_width, fov)


def test_a_360_view_is_a_circular_roll():
    street = np.random.default_rng(1).integers(0, 255, (5, 616, 3), dtype=np.uint8)
    assert np.array_equal(view_canvas(street, 360, 0), street)  # heading 0: already north-aligned
    # a view of heading 90° (east at its centre): its column 0 looks west, which the canvas shows at column W/4
    assert np.array_equal(view_canvas(street, 360, 90), np.roll(street, 154, axis=1))


def test_crop_looks_along_its_heading():
    pano = bearing_panorama(360)  # value - 1 = column; column j looks along 180 + j degrees
    east = crop_view(pano, 90, 90)
    assert east.shape == (3, 90, 2)
    assert east[0, 45, 0] - 1 == 270  # the centre column looks east: 180 + 270 = 90 (mod 360)
    assert east[0, 0, 0] - 1 == 225 and east[0, -1, 0] - 1 == 314  # bearings 45 .. 134
    south = crop_view(pano, 70, 180)
    assert south[0, 35, 0] - 1 == 0  # south is the panorama's column 0: the crop wraps around it
    assert np.array_equal(crop_view(pano, 360, 0), pano)


@pytest.mark.parametrize("fov", [360, 180, 90, 70])
def test_crop_then_canvas_at_the_true_heading_gives_back_the_visible_columns(fov):
    rng = np.random.default_rng(fov)
    width = 720  # 720·f/360 is a whole number of columns for every f here
    pano = rng.integers(1, 255, (6, width, 3), dtype=np.uint8)
    for heading in rng.uniform(0, 360, 5):
        canvas = view_canvas(crop_view(pano, fov, heading), fov, heading)
        assert canvas.shape == pano.shape
        seen = canvas.any(axis=(0, 2))
        assert seen.sum() == round(width * fov / 360)
        assert np.array_equal(canvas[:, seen], pano[:, seen])  # exactly the panorama where the view is
        assert np.array_equal(canvas, north_window(pano, fov, heading))


def test_candidates_hold_the_aligned_canvas_of_each_heading():
    cfg = CrossViewDataConfig(aerial_size=32, pano_size=[16, 64])
    pano = np.random.default_rng(3).integers(0, 255, (16, 64, 3), dtype=np.uint8)
    view = crop_view(pano, 90, 135.0)  # heading 135 = candidate 3 of 8
    tensors, headings = query_candidates(view, cfg, "panorama", 90, 8)
    assert tensors.shape == (8, 3, 32, 32) and np.allclose(headings, np.arange(8) * 45.0)
    truth = image_tensor(align_query(north_window(pano, 90, 135.0), cfg))
    assert tensors.dtype == torch.uint8 and torch.equal(tensors[3], truth)  # normalised on the device
    assert not torch.equal(tensors[2], truth)
    polar_cfg = CrossViewDataConfig(alignment="polar", aerial_size=32, pano_size=[16, 64])
    tensors, _ = query_candidates(view, polar_cfg, "panorama", 90, 8)
    assert tensors.shape == (8, 3, 16, 64)


def test_circular_error_wraps():
    assert np.allclose(circular_error_deg([350, 10, 180, 0], [10, 350, 0, 0]), [20, 20, 180, 0])


@pytest.mark.parametrize("call,match", [
    (lambda v, c: view_canvas(v, 0, 0), r"fov_deg must lie in \(0, 360\]"),
    (lambda v, c: crop_view(v, 361, 0), r"fov_deg must lie in \(0, 360\]"),
    (lambda v, c: query_candidates(v, c, "panorama", 90, 0), "heading_steps must be an int >= 1"),
    (lambda v, c: query_candidates(v, c, "image", 90, 4), "view 'panorama' or 'sphere'"),
])
def test_bad_arguments_say_what_is_wrong(call, match):
    view = np.zeros((8, 16, 3), np.uint8)
    with pytest.raises(ConfigError, match=match):
        call(view, CrossViewDataConfig(aerial_size=32, pano_size=[16, 64]))
