"""views=any_view: the geometry of its three canvases, the items it makes, and the task's check of the loss."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from geoloc import registry
from geoloc.config import ConfigError
from geoloc.tasks.crossview.views import crop_view, view_canvas

from conftest import tiny_task
from helpers.crossview_runs import pairs_of


class Draws:
    """Stands in for the generator: uniform() returns the given values in turn."""

    def __init__(self, *values):
        self.values = list(values)

    def uniform(self, low=0.0, high=1.0):
        return low + (high - low) * self.values.pop(0)


def panorama(w=72, h=4):
    return np.random.default_rng(0).integers(1, 255, (h, w, 3), np.uint8)  # no column is 0


@pytest.mark.parametrize("fov_u,heading_u,offset_u", [(0.5, 0.25, 0.0), (0.1, 0.9, 1.0), (0.99, 0.5, 0.25)])
def test_the_true_and_the_wrong_canvas_are_the_view_at_its_two_bearings(fov_u, heading_u, offset_u):
    """fov and offsets chosen so that W·f/360 and W·d/360 are whole: the canvases are exact."""
    pano = panorama()
    views = registry.build("query_views", {"name": "any_view", "fov_min": 70.0, "fov_max": 360.0,
                                           "full_share": 0.0, "min_offset": 20.0})
    fov = 70 + 290 * fov_u
    fov = round(fov / 5) * 5  # 72 columns: 5 degrees a column
    heading = 360 * heading_u
    offset = 20 + 320 * offset_u
    rng = Draws(0.9, (fov - 70) / 290, heading_u, offset_u)  # full-share draw, fov, heading, offset
    main, (wrong, full) = views(pano, rng)
    view = crop_view(pano, fov, heading)
    assert np.array_equal(main, view_canvas(view, fov, heading))
    assert np.array_equal(wrong, view_canvas(view, fov, heading + offset))
    assert np.array_equal(full, pano)
    assert not np.array_equal(main, wrong)


def test_a_full_share_draw_gives_the_whole_panorama_and_a_rotation_of_it():
    pano = panorama()
    views = registry.build("query_views", {"name": "any_view", "full_share": 1.0})
    main, (wrong, _) = views(pano, Draws(0.0, 0.5, 0.5))  # full, heading 180, offset 180
    assert np.array_equal(main, pano)
    assert np.array_equal(wrong, np.roll(pano, 36, axis=1))


@pytest.mark.parametrize("keys,match", [({"fov_min": 200.0, "fov_max": 100.0}, "fov_min"),
                                        ({"full_share": 1.5}, "full_share"), ({"min_offset": 0.0}, "min_offset"),
                                        ({"fov_max": 400.0}, "fov_max")])
def test_bad_view_keys_are_refused(keys, match):
    with pytest.raises(ConfigError, match=match):
        registry.build("query_views", {"name": "any_view", **keys})


def test_training_items_carry_the_extra_views_and_evaluation_items_do_not(tiny_cvusa):
    section = {"name": "cvusa", "root": str(tiny_cvusa), "aerial_size": 32, "pano_size": [16, 64]}
    from geoloc.tasks.crossview.data_config import parse_dataset
    from geoloc.tasks.crossview.datasets import build

    data, reader = parse_dataset(section)
    train = build(data, reader, "train", train=True, views={"name": "any_view"})
    item = train[(0, 0)]
    assert item["query"].shape == (3, 32, 32) and item["query_views"].shape == (2, 3, 32, 32)
    assert not torch.equal(item["query_views"][0], item["query"])
    assert "query_views" not in build(data, reader, "val", train=False, views={"name": "any_view"})[0]
    assert "query_views" not in pairs_of(section, "train", train=True)[(0, 0)]  # views=single: as before


def test_a_loss_that_cannot_take_the_extra_views_is_refused_before_training(tiny_cvusa):
    from geoloc.tasks.crossview.data_config import parse_dataset
    from geoloc.tasks.crossview.datasets import build

    data, reader = parse_dataset({"name": "cvusa", "root": str(tiny_cvusa), "aerial_size": 32, "pano_size": [16, 64]})
    pairs = build(data, reader, "train", train=True, views={"name": "any_view"})
    with pytest.raises(ConfigError, match="query_views"):
        tiny_task().train_dataloader(pairs, 4, engine=None)  # gms_triplet: no query_views argument
