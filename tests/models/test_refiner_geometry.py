"""The correlation refiner's geometry, brute force: a tile map shifted (and turned) is found at the right lattice
point and heading with no training, and an IPT of a turned panorama is the turned IPT the refiner assumes."""

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from geoloc.data import polar
from geoloc.models.refiners import Refinement
from geoloc.models.refiners.correlation import CorrelationRefiner, correlate, rotate_maps
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


def brute_correlate(query, reference, headings, kernel, overlap, offset=0.0):
    """correlate's definition, cell by cell: the rotated query's central window laid with its centre on every cell
    corner of the tile (the reference map's central n x n, which a margin of (m - n) / 2 cells may surround), the dot
    products summed over the window cells on the map that hold imagery (a non-zero vector), divided by how many
    ("mean") or by the whole window ("window"), or less `offset` for each such cell, over the whole window
    ("evidence")."""
    b, c, n, _ = query.shape
    m = reference.shape[-1]
    p = (m - n) // 2
    rotated = rotate_maps(query, headings)
    start, half = (n - kernel) // 2, kernel // 2
    out = torch.zeros(b, headings.numel(), n + 1, n + 1, dtype=torch.float64)
    for bi in range(b):
        for k in range(headings.numel()):
            window = rotated[bi, k, :, start:start + kernel, start:start + kernel].double()
            for i in range(n + 1):
                for j in range(n + 1):
                    total, cells = 0.0, 0
                    for a in range(kernel):
                        for d in range(kernel):
                            r, q = p + i - half + a, p + j - half + d
                            if 0 <= r < m and 0 <= q < m and bool(reference[bi, :, r, q].abs().sum() > 0):
                                total += float(window[:, a, d] @ reference[bi, :, r, q].double())
                                cells += 1
                    if overlap == "evidence":
                        total -= offset * cells
                    out[bi, k, i, j] = total / (cells if overlap == "mean" else kernel * kernel)
    return out


@pytest.mark.parametrize("overlap", ["mean", "window", "evidence"])
def test_correlate_is_its_brute_force_definition(overlap):
    query, reference = torch.cat([smooth_maps(3, 8, 1), smooth_maps(3, 8, 2)]), torch.cat(
        [smooth_maps(3, 8, 3), smooth_maps(3, 8, 4)])
    headings = torch.tensor([0.0, 30.0])
    found = correlate(query, reference, headings, kernel=4, overlap=overlap, offset=torch.tensor(0.3))
    expected = brute_correlate(query, reference, headings, 4, overlap, offset=0.3)
    assert torch.allclose(found.double(), expected, atol=1e-5)


def test_the_evidence_overlap_needs_its_offset_and_learns_it():
    query, reference = smooth_maps(3, 8, 1), smooth_maps(3, 8, 2)
    with pytest.raises(ValueError, match="offset"):
        correlate(query, reference, torch.zeros(1), kernel=4, overlap="evidence")
    refiner = CorrelationRefiner(channels=4, width=4, overlap="evidence")
    assert refiner.evidence_offset.requires_grad
    assert "evidence_offset" not in CorrelationRefiner(channels=4, width=4).state_dict()  # other refiners unchanged
    images = torch.rand(2, 3, 16, 16)
    refiner(images, images, [0.0]).log_prob[..., 0, 0].sum().backward()  # a corner truth: the charge matters
    assert refiner.evidence_offset.grad is not None and refiner.evidence_offset.grad.abs() > 0


def test_replicate_padding_repeats_the_border_in_every_convolution():
    refiner = CorrelationRefiner(channels=4, width=4, context=1, padding="replicate")
    convs = [m for m in refiner.reference_encoder.modules() if isinstance(m, torch.nn.Conv2d) and m.kernel_size == (3, 3)]
    assert convs and all(m.padding_mode == "replicate" for m in convs)
    assert all(m.padding_mode == "zeros" for m in CorrelationRefiner(channels=4, width=4).modules()
               if isinstance(m, torch.nn.Conv2d))
    with pytest.raises(ValueError, match="padding"):
        CorrelationRefiner(padding="reflect")


def test_a_camera_at_the_edge_scores_as_a_camera_at_the_centre():
    """Unit features, the query exactly the tile around the camera: the mean cosine on the tile is 1 wherever the
    camera stands; dividing by the whole window scored it 0.39 two cells from the corner."""
    tile = F.normalize(smooth_maps(8, 32, seed=7), dim=1)
    for row, col in ((16, 16), (2, 30)):
        query = query_at(tile, row, col)
        mean = correlate(query, tile, torch.zeros(1), kernel=16)[0, 0, row, col]
        window = correlate(query, tile, torch.zeros(1), kernel=16, overlap="window")[0, 0, row, col]
        assert mean == pytest.approx(1.0, abs=1e-4)
        assert window == pytest.approx(1.0 if row == 16 else (10 * 10) / (16 * 16), abs=1e-4)


def test_query_scale_draws_the_query_larger_about_its_centre():
    """A map whose value is each cell's column from the centre, drawn twice as large, reads half of it: the
    output cell q samples the input at q / 2."""
    n = 16
    ramp = (torch.arange(n) + 0.5 - n / 2).float().expand(n, n)[None, None]
    zoomed = rotate_maps(ramp, torch.zeros(1), torch.tensor([2.0]))[0, 0, 0]
    assert torch.allclose(zoomed[:, 4:12], ramp[0, 0, :, 4:12] / 2, atol=1e-5)
    # per tile: each pair drawn at its own scale, as the separate copies would be
    tiles = torch.cat([smooth_maps(4, 16, seed=s) for s in range(3)])
    query = smooth_maps(4, 16, seed=9).expand(3, -1, -1, -1)
    scales = torch.tensor([1.0, 1.13, 0.95])
    together = correlate(query, tiles, torch.tensor([0.0, 90.0]), kernel=8, query_scale=scales)
    for i in range(3):
        alone = correlate(query[:1].contiguous(), tiles[i:i + 1], torch.tensor([0.0, 90.0]), kernel=8,
                          query_scale=scales[i:i + 1])
        assert torch.allclose(together[i:i + 1], alone, atol=1e-5)
    assert not torch.allclose(together[1], correlate(query[:1].contiguous(), tiles[1:2], torch.tensor([0.0, 90.0]),
                                                      kernel=8)[0], atol=1e-3)


@pytest.mark.parametrize("zoom", [1.3, 0.77])
def test_a_tile_of_another_ground_extent_is_matched_at_the_querys_scale(zoom):
    """A tile covering 1 / zoom of the ground the query's frame stands for shows everything zoom times larger: the
    query's map drawn zoom times larger is found where the camera is in that tile, and matches better there than
    drawn as it is or the other way."""
    ground = smooth_maps(8, 32, seed=11)
    tile = rotate_maps(ground, torch.zeros(1), torch.tensor([zoom]))[:, 0]  # the same ground, another extent
    for row, col in ((13, 19), (22, 9)):  # the camera, in the query's frame
        query = query_at(ground, row, col)
        peak = {s: correlate(query, tile, torch.zeros(1), kernel=16, query_scale=torch.tensor([s]))
                for s in (zoom, 1.0, 1.0 / zoom)}
        found = divmod(int(peak[zoom].flatten().argmax()), 33)
        expect = (16 + zoom * (row - 16), 16 + zoom * (col - 16))
        assert abs(found[0] - expect[0]) <= 0.5 and abs(found[1] - expect[1]) <= 0.5
        assert peak[zoom].max() > peak[1.0].max() > peak[1.0 / zoom].max()


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


def brute_force_blur(prob: np.ndarray, sigma: float) -> np.ndarray:
    """Each lattice point's Gaussian-weighted sum of the probabilities within 3 sigma (on the map only), weights
    normalised over the whole kernel, by loops."""
    rows, cols = prob.shape
    radius = int(np.ceil(3 * sigma))
    offsets = np.arange(-radius, radius + 1)
    weight = np.exp(-0.5 * (offsets / sigma) ** 2)
    weight /= weight.sum()
    out = np.zeros_like(prob)
    for i in range(rows):
        for j in range(cols):
            for a, wa in zip(offsets, weight):
                for b, wb in zip(offsets, weight):
                    if 0 <= i + a < rows and 0 <= j + b < cols:
                        out[i, j] += wa * wb * prob[i + a, j + b]
    return out


def test_peak_smoothing_answers_where_the_mass_is_not_the_narrow_spike():
    """A narrow spike (one lattice point, 0.2 of the mass) beside a broad bump (0.8): the raw peak is the spike,
    the smoothed answer the bump's centre, at the lattice point a brute-force blur puts highest; the mass within
    a radius is counted around the smoothed answer."""
    rows = cols = 33
    ys, xs = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    bump = np.exp(-((ys - 20.0) ** 2 + (xs - 9.0) ** 2) / (2 * 3.0 ** 2))
    prob = 0.8 * bump / bump.sum()
    prob[6, 26] += 0.2
    out = Refinement(torch.from_numpy(np.log(prob))[None, None].float(), torch.zeros(1))
    raw = out.position()[0] * (rows - 1)
    assert torch.allclose(raw, torch.tensor([6.0, 26.0]), atol=0.1)
    smoothing = 2.0 / (rows - 1)  # sigma of two lattice steps
    smoothed = out.position(smoothing)[0] * (rows - 1)
    expected = np.unravel_index(brute_force_blur(prob, 2.0).argmax(), prob.shape)
    assert tuple(torch.round(smoothed).int().tolist()) == tuple(int(v) for v in expected) == (20, 9)
    extent = torch.tensor([[32.0, 32.0]])  # 1 m a lattice step
    assert out.mass_within(6.0, extent, smoothing).item() > 0.5 > out.mass_within(6.0, extent).item()
    read = out.position(smoothing)  # an answer already read is not read again
    assert out.mass_within(6.0, extent, smoothing, at=read).item() == out.mass_within(6.0, extent, smoothing).item()


def test_peak_smoothing_is_the_raw_peak_for_a_smooth_map_and_never_leaves_the_tile():
    """On one Gaussian bump the smoothed peak is the raw one (sub-lattice, within 0.1 step); a bump at the corner
    stays on the tile."""
    rows = cols = 17
    ys, xs = torch.meshgrid(torch.arange(rows).float(), torch.arange(cols).float(), indexing="ij")
    for peak in ((5.3, 11.6), (0.0, 16.0)):
        logit = -((ys - peak[0]) ** 2 + (xs - peak[1]) ** 2) / 2.0
        out = Refinement(F.log_softmax(logit.flatten(), 0).reshape(1, 1, rows, cols), torch.zeros(1))
        got = out.position(0.1)[0]
        assert ((got >= 0) & (got <= 1)).all()
        assert torch.allclose(got * (rows - 1), torch.tensor(peak), atol=0.1 if peak[0] else 1.0), (peak, got)
