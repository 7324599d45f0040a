"""Nuisances drawn apart per view (geoloc/synthetic/nuisance.py, SynthConfig.view_nuisance): off by default with every
pixel and marker as before, deterministic when on, each view its own draws within the documented ranges."""

from __future__ import annotations

import numpy as np
import pytest

from geoloc.synthetic import nuisance
from geoloc.synthetic.samples import render_pair
from geoloc.synthetic.world_config import resolve


def test_draws_stay_in_their_ranges_and_the_two_views_differ():
    rng = np.random.default_rng(0)
    draws = [nuisance.draw(rng, 0.5) for _ in range(200)]
    assert all(np.exp(-0.05) <= d.tile_scale <= np.exp(0.05) for d in draws)
    assert all(np.exp(-0.1) <= d.height_factor <= np.exp(0.1) for d in draws)
    assert all(-1.5 <= d.pitch_deg <= 1.5 and 0 <= d.haze <= 0.125 for d in draws)
    assert all(np.exp(-0.1) <= d.gamma <= np.exp(0.1) for d in draws)
    gains = np.log(np.stack([d.class_gains for d in draws]))
    assert gains.std() == pytest.approx(0.075, rel=0.1)  # 0.15 s, s = 0.5
    assert not np.array_equal(draws[0].class_gains, draws[1].class_gains)


def test_a_scaled_tile_is_an_even_number_of_cells_inside_the_world():
    assert nuisance.scaled_tile_m(144.0, 0.5625, 1.05, 334) == pytest.approx(268 * 0.5625)
    assert nuisance.scaled_tile_m(144.0, 0.5625, 2.0, 333) == pytest.approx(332 * 0.5625)  # clipped to the world
    assert nuisance.horizon_with_pitch(0.58, 360.0 / 616 * 112 * 0.1, 112, 616) == pytest.approx(0.68)


def test_off_by_default_the_marker_is_unchanged():
    """(The pixels: tests/synthetic/test_render_digests.py pins the default renders.)"""
    cfg, _ = resolve("cvusa", "small", {})
    assert cfg.view_nuisance is None and "view_nuisance" not in cfg.as_dict()
    on, _ = resolve("cvusa", "small", {"view_nuisance": 0.5})
    assert on.as_dict()["view_nuisance"] == 0.5
    with pytest.raises(ValueError, match="view_nuisance"):
        resolve("cvusa", "small", {"view_nuisance": 1.5})


def test_on_it_is_deterministic_and_moves_both_views():
    off, _ = resolve("cvusa", "small", {})
    on, _ = resolve("cvusa", "small", {"view_nuisance": 1.0})
    base, a, b = (render_pair(c, 0, "train", 5, sphere=False) for c in (off, on, on))
    for view in ("aerial", "pano"):
        assert np.array_equal(a[view], b[view])
        assert np.abs(a[view].astype(int) - base[view]).mean() > 2
    # the place is the same one: the world stream is untouched, so the street labels differ only by the camera
    assert a["style"] == base["style"]


def test_layouts_that_do_not_draw_it_refuse_it(tmp_path):
    from geoloc.synthetic import generate

    with pytest.raises(ValueError, match="cvusa and cvact layouts only"):
        generate("vigor", tmp_path / "v", preset="vigor_tiny", view_nuisance=0.5)
    assert not (tmp_path / "v").exists()
