"""The correlation refiner's geometry, brute force: a tile map shifted (and turned) is found at the right lattice
point and heading with no training, and an IPT of a turned panorama is the turned IPT the refiner assumes."""

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from geoloc.data import polar
from geoloc.models.refiners import Refinement
from geoloc.models.refiners.correlation import correlate, rotate_maps
from geoloc.tasks.crossview.views import crop_view


def smooth_maps(c: int, n: int, seed: int) -> torch.Tensor:
    """1 x c x n x n random features, blurred so a rotation's bilinear resampling keeps them."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(1, c, n, n, generator=g)
    kernel = torch.ones(c, 1, 3, 3) / 9.0
    return F.conv2d(F.conv2d(x, kernel, padding=1, groups=c), kernel, padding=1, groups=c)


def query_at(tile: torch.Tensor, row: int, col: int) -> torch.Tensor:
    """The tile's map moved so that lattice point (row, col) lies at the map's centre (cell corner n/2), zeros
    where it leaves the tile: what a query standing at (row, col) sees, north up."""
    n = tile.shape[-1]
    out = torch.zeros_like(tile)
    for i in range(n):
        for j in range(n):
            si, sj = i - n // 2 + row, j - n // 2 + col
            if 0 <= si < n and 0 <= sj < n:
                out[..., i, j] = tile[..., si, sj]
    return out


@pytest.mark.parametrize("row,col", [(16, 16), (9, 21), (24, 5), (12, 27)])
def test_a_shifted_tile_is_found_at_its_lattice_point(row, col):
    tile = smooth_maps(8, 32, seed=row * 100 + col)
    scores = correlate(query_at(tile, row, col), tile, torch.zeros(1), kernel=16)
    assert scores.shape == (1, 1, 33, 33)
    best = int(scores.flatten().argmax())
    assert divmod(best, 33) == (row, col)


@pytest.mark.parametrize("heading", [0.0, 70.0, 180.0, 290.0])
def test_a_turned_query_is_found_at_its_heading_and_position(heading):
    tile = smooth_maps(8, 32, seed=int(heading))
    north_up = query_at(tile, 14, 18)
    # the query seen at `heading` is its north-up map turned anticlockwise by the heading
    seen = rotate_maps(north_up, torch.tensor([-heading]))[:, 0]
    bins = torch.arange(36) * 10.0
    scores = correlate(seen, tile, bins, kernel=16)
    k, position = divmod(int(scores.flatten().argmax()), 33 * 33)
    assert bins[k].item() == heading
    assert divmod(position, 33) == (14, 18)


def test_one_query_expanded_over_its_tiles_scores_as_the_copied_query():
    """An app refines one query in its top-k tiles by expanding its map (stride 0): the rotations and transforms
    are then computed once, and the scores must be those of B separate copies."""
    tiles = torch.cat([smooth_maps(8, 32, seed=s) for s in range(4)])
    turned = rotate_maps(query_at(tiles[2:3], 14, 18), torch.tensor([-70.0]))[:, 0]
    bins = torch.arange(36) * 10.0
    expanded = turned.expand(4, -1, -1, -1)
    assert expanded.stride(0) == 0
    shared = correlate(expanded, tiles, bins, kernel=16)
    copied = correlate(expanded.contiguous(), tiles, bins, kernel=16)
    assert shared.shape == copied.shape == (4, 36, 33, 33)
    assert torch.allclose(shared, copied, atol=1e-5)
    k, position = divmod(int(shared[2].flatten().argmax()), 33 * 33)  # found in its own tile, as before
    assert (bins[k].item(), divmod(position, 33)) == (70.0, (14, 18))


def test_rotate_maps_turns_clockwise():
    """A mark above the centre (north) turned by 90 degrees lands right of it (east)."""
    maps = torch.zeros(1, 1, 9, 9)
    maps[0, 0, 1, 4] = 1.0
    turned = rotate_maps(maps, torch.tensor([90.0]))[0, 0, 0]
    assert divmod(int(turned.argmax()), 9) == (4, 7)


def test_the_ipt_of_a_turned_panorama_is_the_turned_ipt():
    """crop_view(panorama, 360, h) (the view of heading h) aligned by IPT, turned clockwise by h, is the north-up
    IPT: the rotation the refiner tries is the heading of views.py."""
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 255, (32, 144, 3)).astype(np.float32)
    wrapped = np.concatenate([noise[:, -16:], noise, noise[:, :16]], 1)  # blur around the circle
    pano = np.clip(cv2.GaussianBlur(wrapped, (0, 0), 3.0)[:, 16:-16] * 4 - 384, 0, 255).astype(np.uint8)
    north = polar.street_to_aerial(pano, (48, 48)).astype(np.float32)
    to_map = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None]  # noqa: E731
    inner = (slice(None), slice(8, 40), slice(8, 40))  # inside the turned square's inscribed circle
    candidates = torch.arange(36) * 10.0
    for heading in (40.0, 130.0, 250.0):
        view = polar.street_to_aerial(crop_view(pano, 360.0, heading), (48, 48)).astype(np.float32)
        turned = rotate_maps(to_map(view), candidates)[0]  # K x 3 x 48 x 48
        errors = [(t - to_map(north)[0])[inner].abs().mean().item() for t in turned]
        assert candidates[int(np.argmin(errors))].item() == heading, errors


def test_refinement_estimates_and_nll_from_a_known_map():
    """A map peaked between lattice points reads back at the peak; the heading between bins too; the soft-target
    NLL is smallest at the truth."""
    rows = cols = 17
    ys, xs = torch.meshgrid(torch.arange(rows).float(), torch.arange(cols).float(), indexing="ij")
    peak = (5.3, 11.6)
    position_logit = -((ys - peak[0]) ** 2 + (xs - peak[1]) ** 2) / 2.0
    headings = torch.arange(12) * 30.0
    heading_logit = -((headings - 95.0 + 180) % 360 - 180) ** 2 / (2 * 30.0 ** 2)
    logits = heading_logit[:, None, None] + position_logit[None]
    log_prob = F.log_softmax(logits.flatten(), 0).reshape(1, 12, rows, cols)
    out = Refinement(log_prob, headings)
    got = out.position()[0] * (rows - 1)
    assert torch.allclose(got, torch.tensor(peak), atol=0.05)
    assert abs(out.heading().item() - 95.0) < 3.0
    truth = torch.tensor([[peak[0] / 16, peak[1] / 16]])
    near = out.nll(truth, torch.tensor([95.0]))
    far = out.nll(torch.tensor([[0.8, 0.2]]), torch.tensor([275.0]))
    assert near < far
    mass = out.mass_within(2.0, torch.tensor([[16.0, 16.0]]))  # 1 m per lattice step: a disc of radius 2
    assert 0.5 < mass.item() < 1.0
