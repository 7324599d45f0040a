"""Tiles read with a margin (geoloc/data/tile_context.py): a world image cut into half-overlapping tiles, as VIGOR
cuts its cities, is put back together around each tile exactly, and where no tile lies the margin says so."""

import numpy as np
import pytest

from geoloc.data.geo import offset_to_latlon
from geoloc.data.tile_context import (TileContext, at_side, margin_pixels, own_pixels, stitched, stitched_side,
                                     tile_neighbours, tile_size)

ORIGIN = (41.88, -87.63)  # Chicago
TILE_PX, TILE_M = 16, 20.0  # 1.25 m a pixel


def world_tiles(n: int, seed: int = 0):
    """A random world image and its n x n tiles of TILE_PX pixels, each half a tile from the next (row-major from the
    north-west), with their centres' (east, north) metres and (lat, lon)."""
    step = TILE_PX // 2
    side = step * (n + 1)
    world = np.random.default_rng(seed).integers(0, 256, (side, side, 3), dtype=np.uint8)
    tiles, xy = [], []
    for row in range(n):
        for col in range(n):
            tiles.append(world[row * step:row * step + TILE_PX, col * step:col * step + TILE_PX])
            centre_px = np.array([col * step + step, row * step + step])  # (x, y) pixels, y down
            xy.append([centre_px[0] * TILE_M / TILE_PX, -centre_px[1] * TILE_M / TILE_PX])
    xy = np.array(xy)
    return world, tiles, xy, offset_to_latlon(ORIGIN, xy[:, 0], xy[:, 1])


def expected(world, index: int, n: int, margin_px: int):
    """The world cut around tile `index` with margin_px beyond each edge; coverage 0 off the world."""
    step = TILE_PX // 2
    row, col = divmod(index, n)
    top, left = row * step - margin_px, col * step - margin_px
    size = TILE_PX + 2 * margin_px
    out = np.zeros((size, size, 4), np.uint8)
    for y in range(size):
        for x in range(size):
            if 0 <= top + y < world.shape[0] and 0 <= left + x < world.shape[1]:
                out[y, x, :3], out[y, x, 3] = world[top + y, left + x], 255
    return out


@pytest.mark.parametrize("kind", ["latlon", "xy"])
def test_the_neighbours_are_the_tiles_half_a_tile_away(kind):
    _, _, xy, latlon = world_tiles(4)
    positions = latlon if kind == "latlon" else xy
    neighbours = tile_neighbours(positions, np.full((16, 2), TILE_M), kind)
    assert neighbours[5].tolist() == [[0, 1, 2], [4, 5, 6], [8, 9, 10]]  # row 0 north, column 0 west
    assert neighbours[0].tolist() == [[-1, -1, -1], [-1, 0, 1], [-1, 4, 5]]  # the north-west corner
    assert neighbours[15].tolist() == [[10, 11, -1], [14, 15, -1], [-1, -1, -1]]
    shuffled = np.random.default_rng(1).permutation(16)  # the order of the list does not matter
    again = tile_neighbours(positions[shuffled], np.full((16, 2), TILE_M), kind)
    back = np.where(again >= 0, shuffled[np.maximum(again, 0)], -1)
    assert (back[np.argsort(shuffled)] == neighbours).all()


def test_a_tile_off_the_grid_by_more_than_the_tolerance_is_no_neighbour():
    _, _, xy, _ = world_tiles(2)
    moved = xy.copy()
    moved[1, 0] += 0.2 * TILE_M / 2  # twice the tolerance of a tenth of a half-tile
    assert tile_neighbours(moved, np.full((4, 2), TILE_M), "xy")[0, 1, 2] == -1
    moved[1, 0] = xy[1, 0] + 0.05 * TILE_M / 2
    assert tile_neighbours(moved, np.full((4, 2), TILE_M), "xy")[0, 1, 2] == 1


@pytest.mark.parametrize("margin", [0.25, 0.5, 0.125])
def test_a_stitched_tile_is_the_world_around_it(margin):
    world, tiles, xy, _ = world_tiles(4)
    neighbours = tile_neighbours(xy, np.full((16, 2), TILE_M), "xy")
    for index in (5, 0, 3, 15, 9):
        out = stitched(index, neighbours[index], lambda i: tiles[i], margin)
        assert np.array_equal(out, expected(world, index, 4, int(round(margin * TILE_PX)))), index
        assert np.array_equal(own_pixels(out, margin), tiles[index]) and own_pixels(out, margin).flags.c_contiguous


def test_a_missing_neighbour_is_made_up_by_the_others_and_a_missing_tile_gives_none():
    """Each margin pixel lies on two tiles beside the tile (the half-overlap): the east one's loss is made up by the
    north-east and south-east ones; without all three the east margin is uncovered, and black."""
    world, tiles, xy, _ = world_tiles(3)
    neighbours = tile_neighbours(xy, np.full((9, 2), TILE_M), "xy")
    full = expected(world, 4, 3, 4)
    assert np.array_equal(stitched(4, neighbours[4], lambda i: None if i == 5 else tiles[i], 0.25), full)
    out = stitched(4, neighbours[4], lambda i: None if i in (2, 5, 8) else tiles[i], 0.25)
    east = slice(4 + TILE_PX, None)
    assert (out[:, east] == 0).all()
    assert np.array_equal(out[:, :4 + TILE_PX], full[:, :4 + TILE_PX])
    assert stitched(4, neighbours[4], lambda i: None if i == 4 else tiles[i], 0.25) is None
    with pytest.raises(ValueError, match="half a tile"):
        stitched(4, neighbours[4], lambda i: tiles[i], 0.6)


def test_at_side_keeps_coverage_only_where_every_source_pixel_had_it():
    world, tiles, xy, _ = world_tiles(2)
    context = TileContext(lambda i: tiles[i], tile_neighbours(xy, np.full((4, 2), TILE_M), "xy"), 0.25)
    out = context.image(0, side=8)
    assert out.shape == (8 + 2 * margin_pixels(8, 0.25), 12, 4)[:1] * 2 + (4,)
    assert (out[2:, 2:, 3] == 255).all() and (out[:2, :, 3] == 0).all() and (out[:, :2, 3] == 0).all()
    canvas = context.image(0)
    assert np.array_equal(at_side(canvas, 8, 0.25), out)
    assert tile_size(canvas.shape[0], 0.25) == TILE_PX
    assert stitched_side(8, 0.25) == out.shape[0] == out.shape[1]


def test_tile_size_inverts_the_canvas_for_every_side():
    for margin in (0.1, 0.25, 0.33, 0.5):
        for h in range(1, 700):
            assert tile_size(h + 2 * int(round(margin * h)), margin) == h
