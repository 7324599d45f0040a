"""The refiner's training item with a margin (refiner.margin): the stitched tile turns and mirrors with the tile and
its truth, and the coverage channel marks the ground no tile covers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from geoloc.data.io import read_rgb

from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.data.tile_context import TileContext
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.refine import RefineConfig
from geoloc.tasks.crossview.refine_items import refine_item, tile_input
from geoloc.tasks.crossview.transforms import turned_tile

from data.test_tile_context import TILE_M, TILE_PX, world_tiles


@pytest.fixture
def grid_split(tmp_path):
    """A 3 x 3 grid of half-overlapping 16 px tiles (as PNG files) and one query at the centre of the centre tile's pixel (4, 10)."""
    world, tiles, _, latlon = world_tiles(3, seed=4)
    paths = []
    for i, tile in enumerate(tiles):
        paths.append(tmp_path / f"t{i}.png")
        cv2.imwrite(str(paths[-1]), cv2.cvtColor(tile, cv2.COLOR_RGB2BGR))
    split = RetrievalSplit("grid", tmp_path, ["q0"], paths, positives=[4], reference_latlon=latlon,
                           reference_size_px=np.full((9, 2), TILE_PX), reference_metres_per_px=np.full(9, TILE_M / TILE_PX),
                           query_tile_px=[[4.5, 10.5]])
    return world, split


def test_the_stitched_tile_turns_with_the_tile_and_the_truth(grid_split):
    """Under the joint flip / rotation the stitched tile is the turned stitched tile, and the turned truth still
    points at the query's pixel (its colour, in a world of random colours)."""
    _, split = grid_split
    cfg = CrossViewDataConfig(name="vigor", aerial_size=TILE_PX, pano_size=[8, 32], joint_flip_rotate=True)
    refine = RefineConfig(margin=0.25)
    context = TileContext.of(split, refine.margin)
    street = np.random.default_rng(0).integers(0, 256, (16, 64, 3), dtype=np.uint8)
    still = context.image(4, TILE_PX)
    assert still.shape == (24, 24, 4) and (still[..., 3] == 255).all()  # the centre tile: every neighbour is there
    query_colour = still[4 + 4, 4 + 10, :3]  # the query stands at the centre of the tile's pixel (4, 10)
    seen = set()
    for seed in range(12):
        rng = np.random.default_rng(seed)
        turns, flip = int(rng.integers(4)), bool(rng.integers(2))  # the draws refine_item makes first
        item = refine_item(split, 0, street, cfg, refine, np.random.default_rng(seed), context)
        wide = item["refine_reference"]
        expected = turned_tile(still, turns, flip)
        assert torch.equal(wide, tile_input(expected, TILE_PX))
        # the retrieval inputs' tile, cut from the same decoded canvas, is the tile file's image turned alike
        assert np.array_equal(item["aerial"], turned_tile(read_rgb(split.references[4]), turns, flip))
        row, col = (item["tile_px"].numpy() * TILE_PX + 4).astype(int)  # the pixel of the stitched tile under it
        assert (expected[row, col, :3] == query_colour).all()
        seen.add((turns, flip))
    assert len(seen) >= 4


def test_an_uncovered_margin_is_zero_in_the_fourth_channel(grid_split):
    _, split = grid_split
    cfg = CrossViewDataConfig(name="vigor", aerial_size=TILE_PX, pano_size=[8, 32])
    street = np.zeros((16, 64, 3), np.uint8)
    corner = RetrievalSplit("corner", split.root, ["q0"], split.references, positives=[0],
                            reference_latlon=split.reference_latlon, reference_size_px=split.reference_size_px,
                            reference_metres_per_px=split.reference_metres_per_px, query_tile_px=[[4.0, 10.0]])
    item = refine_item(corner, 0, street, cfg, RefineConfig(margin=0.25), None,
                       TileContext.of(corner, 0.25))
    covered = item["refine_reference"][3]
    assert (covered[:4] == 0).all() and (covered[:, :4] == 0).all()  # north and west of the north-west tile
    assert (covered[4:, 4:] == 1).all()
