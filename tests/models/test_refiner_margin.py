"""The refiner's tile margin (refiner.margin): the correlation over a tile map with ground around it, against its
brute-force definition, and a camera at the edge found with the margin where the tile alone misses it."""

import pytest
import torch
import torch.nn.functional as F

from geoloc.models.refiners.correlation import CorrelationRefiner, correlate
from models.test_refiner_geometry import brute_correlate, query_at, smooth_maps


@pytest.mark.parametrize("overlap", ["mean", "window", "evidence"])
def test_correlate_with_a_margin_is_its_brute_force_definition(overlap):
    query = torch.cat([smooth_maps(3, 8, 1), smooth_maps(3, 8, 2)])
    reference = torch.cat([smooth_maps(3, 12, 3), smooth_maps(3, 12, 4)])
    reference[0, :, :, 10:] = 0  # no imagery east of the first tile's margin's first column
    reference[1, :, :2, :] = 0  # none north of the second tile
    headings = torch.tensor([0.0, 30.0])
    found = correlate(query, reference, headings, kernel=4, overlap=overlap, offset=torch.tensor(0.3))
    expected = brute_correlate(query, reference, headings, 4, overlap, offset=0.3)
    assert found.shape == (2, 2, 9, 9)
    assert torch.allclose(found.double(), expected, atol=1e-5)


def test_a_margin_of_nothing_scores_as_the_tile_alone():
    """A margin whose cells hold no imagery changes no score: the tile alone's correlation, cell for cell."""
    query, tile = smooth_maps(3, 8, 5), smooth_maps(3, 8, 6)
    wide = F.pad(tile, (2, 2, 2, 2))
    for overlap in ("mean", "window"):
        alone = correlate(query, tile, torch.zeros(1), kernel=8, overlap=overlap)
        assert torch.allclose(correlate(query, wide, torch.zeros(1), kernel=8, overlap=overlap), alone, atol=1e-5)
    assert torch.allclose(alone.double(), brute_correlate(query, tile, torch.zeros(1), 8, "window"), atol=1e-5)


def test_a_camera_near_the_edge_is_found_with_the_margin():
    """The query is the world around a camera two cells inside the tile's north edge; the margin of 8 cells puts 26 of
    its window's 32 rows on imagery where the tile alone has 18, and the true corner is the best."""
    world = F.normalize(smooth_maps(8, 48, seed=11), dim=1)
    tile, wide = world[..., 8:40, 8:40], world
    query = query_at(world, 8 + 2, 8 + 16)[..., 8:40, 8:40]  # the camera at the world's corner (10, 24): tile's (2, 16)
    scores = correlate(query, wide, torch.zeros(1), kernel=32)
    assert divmod(int(scores.flatten().argmax()), 33) == (2, 16)
    assert scores[0, 0, 2, 16] == pytest.approx(1.0, abs=1e-4)
    on_imagery = correlate(query, wide, torch.zeros(1), kernel=32, overlap="window")[0, 0, 2, 16]
    alone = correlate(query, tile, torch.zeros(1), kernel=32, overlap="window")[0, 0, 2, 16]
    assert on_imagery == pytest.approx(26 * 32 / (32 * 32), abs=1e-4)
    assert alone == pytest.approx(18 * 32 / (32 * 32), abs=1e-4)


def test_the_reference_encoder_reads_the_covered_mask():
    refiner = CorrelationRefiner(channels=4, width=4)
    images = torch.rand(2, 4, 24, 24)
    images[:, 3] = 1.0
    images[1, 3, :, 20:] = 0.0  # the east margin of the second tile has no imagery
    images[1, 3, 5, 3] = 0.0  # nor one pixel: its cell is dropped
    maps = refiner.encode_reference(images)
    assert maps.shape == (2, 4, 12, 12)
    norm = maps.norm(dim=1)
    assert torch.allclose(norm[0], torch.ones(12, 12), atol=1e-5)
    assert (norm[1, :, 10:] == 0).all() and norm[1, 2, 1] == 0
    assert torch.allclose(norm[1, :, :10].flatten()[norm[1, :, :10].flatten() > 0], torch.tensor(1.0), atol=1e-5)
    out = refiner(torch.rand(2, 3, 16, 16), images, [0.0])
    assert out.position_log_prob.shape[-2:] == (9, 9)  # the tile's lattice alone: (16 / 2) + 1


def test_a_reference_smaller_than_the_query_or_an_odd_margin_is_refused():
    query = smooth_maps(3, 8, 1)
    for side in (6, 9):
        with pytest.raises(ValueError, match="margin"):
            correlate(query, smooth_maps(3, side, 2), torch.zeros(1), kernel=4)


def test_the_matcher_lays_one_query_on_tiles_with_and_without_a_margin_as_match_does():
    """The app's path (the query turned once, its windows laid once for each size of reference map) gives match's
    answer for the query map expanded to the tiles, on 12 x 12 maps with a margin and on 8 x 8 ones without."""
    refiner = CorrelationRefiner(channels=3, width=4, kernel_frac=1.0, heading_bins=4).eval()
    query = F.normalize(smooth_maps(3, 8, 7), dim=1)
    matched = refiner.matcher(query, [0.0, 90.0])
    for side, seed in ((12, 8), (8, 9), (12, 10)):
        tiles = F.normalize(smooth_maps(3, side, seed), dim=1)
        tiles = torch.cat([tiles, tiles.flip(-1)])
        expected = refiner.match(query.expand(2, -1, -1, -1), tiles, [0.0, 90.0]).position_log_prob
        assert torch.allclose(matched(tiles).position_log_prob, expected, atol=1e-5)
