"""An app's refinement of one query in its top-k tiles runs over the tiles in parts: each part's tiles are decoded
as it is taken, so the memory does not grow with topk, and the answer is the one a single batch of every tile
gives, to the bit (the query's map turned once per query scale)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from geoloc.tasks.crossview.encoder import CrossViewEncoder
from geoloc.tasks.crossview.refine import offset_m

from conftest import TINY, compose_train
from helpers.crossview_runs import task_of

REFINER = ["refiner=correlation", "refiner.channels=4", "refiner.width=4", "refiner.heading_bins=8",
           "refiner.size=32"]


def encoder_of(*overrides) -> CrossViewEncoder:
    cfg = compose_train([*[t for t in TINY if not t.startswith("dataset=")], "dataset=vigor", "run_dir=unused",
                         "dataset.root=unused", *REFINER, *overrides])
    torch.manual_seed(0)
    views = {"task_info": {"query_view": {"train": "sphere", "val": "sphere"}}}  # VIGOR's, as a checkpoint records
    return CrossViewEncoder(task_of(cfg), cfg, views, "unused.pt", torch.device("cpu"))


def one_batch(encoder, query, tiles, extent, radius_m=5.0):
    """The refinement of every tile in one batch: the query's map expanded to them (as the apps did)."""
    maps = encoder.refiner.encode_query(query)
    inputs = torch.stack([encoder.refine_tile(tile) for tile in tiles])
    references = encoder.refiner.encode_reference(inputs)
    scale = encoder.refine_config.query_scale(extent)
    scales = {} if scale is None else {"query_scale": scale}  # a plug-in may take no scale
    found = encoder.refiner.match(maps.expand(len(tiles), *maps.shape[1:]), references,
                                  encoder.refine_config.candidates(8), **scales)
    smoothing = encoder.refine_config.peak_smoothing
    return {"offset_m": offset_m(found.position(smoothing).double().numpy(), extent),
            "heading_offset_deg": found.heading().numpy(),
            "mass": found.mass_within(radius_m, torch.as_tensor(extent, dtype=torch.float32), smoothing).numpy(),
            "maps": found.position_log_prob.exp().numpy()}


@pytest.mark.parametrize("scales", [1, 2])
@torch.no_grad()
def test_the_refiner_takes_the_tiles_in_parts_decoded_as_taken_with_the_one_batch_answer(scales):
    encoder = encoder_of("refiner.orientation_noise_deg=180", "refiner.query_extent_m=60",
                         "refiner.peak_smoothing=0.1")
    rng = np.random.default_rng(0)
    tiles = [rng.integers(0, 255, (40 + k % 3, 40, 3), np.uint8) for k in range(11)]
    extent = np.array([[70.0, 70.0] if k % scales == 0 else [55.0, 55.0] for k in range(11)])  # 1 or 2 scales
    query = encoder.refine_query(rng.integers(0, 255, (16, 64, 3), np.uint8), 30.0)
    events = []
    encode = encoder.refiner.encode_reference

    def tile(i):
        events.append(("decoded", i))
        return tiles[i]

    encoder.refiner.encode_reference = lambda inputs: events.append(("encoded", len(inputs))) or encode(inputs)
    parts = encoder.refine(query, tile, extent, chunk=3)
    del encoder.refiner.encode_reference
    whole = one_batch(encoder, query, tiles, extent)
    for key, value in whole.items():
        assert parts[key].shape == value.shape and np.array_equal(parts[key], value), key
    assert parts["tile_size_px"].tolist() == [list(t.shape[:2]) for t in tiles]
    assert sorted(i for kind, i in events if kind == "decoded") == list(range(11))  # each tile decoded once
    held = 0
    for kind, count in events:  # at most one part of decoded tiles waits for the encoder
        held = held + 1 if kind == "decoded" else held - count
        assert 0 <= held <= 3
    assert max(count for kind, count in events if kind == "encoded") == 3
    assert encoder.refine(query, lambda i: None if i == 7 else tiles[i], extent, chunk=3) is None  # unreadable


@torch.no_grad()
def test_a_plugin_refiner_without_a_matcher_is_matched_part_by_part():
    from plugins.dot_map import DotMap

    encoder = encoder_of()
    encoder.refiner = DotMap(4).eval()
    rng = np.random.default_rng(2)
    tiles = [rng.integers(0, 255, (40, 40, 3), np.uint8) for _ in range(7)]
    extent = np.full((7, 2), 70.0)
    query = encoder.refine_query(rng.integers(0, 255, (16, 64, 3), np.uint8), 0.0)
    parts, whole = encoder.refine(query, tiles.__getitem__, extent, chunk=2), one_batch(encoder, query, tiles, extent)
    for key, value in whole.items():  # its own kernels may round a part otherwise than the whole batch
        np.testing.assert_allclose(parts[key], value, rtol=1e-5, atol=1e-7, err_msg=key)


@torch.no_grad()
def test_the_localizer_refines_its_topk_in_parts_with_the_one_batch_answer(tmp_path):
    """Localizer._refine over 11 tiles (two parts of REFINE_CHUNK): each tile's refined position is the one-batch
    refinement's offset from its centre, and its pixel is given in the tile's own size."""
    import cv2
    from geoloc.apps.localize import Localizer
    from geoloc.tasks.crossview import LocalizationResult
    from geoloc.gallery.places import Places

    encoder = encoder_of()
    rng = np.random.default_rng(1)
    tiles = [rng.integers(0, 255, (48, 44 + k, 3), np.uint8) for k in range(11)]
    for k, tile in enumerate(tiles):
        cv2.imwrite(str(tmp_path / f"{k}.png"), tile[..., ::-1])
    centres = np.array([[100.0 * k, -20.0 * k] for k in range(11)])
    extent = np.full((11, 2), 70.0)
    places = Places(tmp_path, "xy", [f"{k}.png" for k in range(11)], centres, {}, extent)
    localizer = Localizer(encoder, None, places, {"query_view": "sphere"})
    image = rng.integers(0, 255, (16, 64, 3), np.uint8)
    topk = [{**places.reference(k), "rank": k + 1, "score": 0.5, "heading_deg": 30.0} for k in range(11)]
    answer = LocalizationResult(None, 360.0, 30.0, "given", topk, positions="xy")
    localizer._refine(answer, image)
    whole = one_batch(encoder, encoder.refine_query(image, 30.0, "sphere"), tiles, extent)
    for k, hit in enumerate(answer.topk):
        refined = hit["refined_position"]
        assert [refined["x_m"], refined["y_m"]] == (centres[k] + whole["offset_m"][k]).tolist()
        assert refined["mass_5m"] == float(whole["mass"][k]) and refined["tile_size_px"] == [48, 44 + k]
    assert np.array_equal(answer.probability_map, whole["maps"][0])
