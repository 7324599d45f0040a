"""Polar transforms (docs/conventions.md "Polar transform" and "IPT"): SAFA aerial -> polar and the paper's IPT
street -> aerial-like."""
import math

import cv2
import numpy as np
import pytest
from geoloc.data import polar
from geoloc.data.polar import aerial_to_polar, street_to_aerial

from conftest import REALDATA

# cv2.remap quantises bilinear weights to 1/32 pixel: on uint8 noise that is up to ~255/32 per axis, plus rounding.
REMAP_TOL = 2 * 255 / 32 + 1


# ---- independent scalar evaluation of the formulas ------------------------------------------------------------
def safa_coord(i, j, s, h, w):
    r = (s / 2) / h * (h - 1 - i)
    return s / 2 + r * math.cos(2 * math.pi * j / w), s / 2 - r * math.sin(2 * math.pi * j / w)  # (row, col)


def ipt_coord(y, x, h_s, w_s, h_a, w_a):
    dy, dx = y - h_a / 2, x - w_a / 2
    r = math.hypot(dx, dy)
    row = (h_s - 1) - math.sqrt(2) * (h_s / h_a) * r  # r rows above the bottom row
    phi = math.atan2(-dx, dy) % (2 * math.pi)  # SAFA: (drow, dcol) = r (cos phi, -sin phi)
    return row, w_s * phi / (2 * math.pi)


def bilinear(img, row, col, wrap_cols=False):
    h, w = img.shape[:2]
    r0, c0 = math.floor(row), math.floor(col)
    fr, fc = row - r0, col - c0
    out = np.zeros(img.shape[2:], dtype=np.float64)
    for rr, wr in ((r0, 1 - fr), (r0 + 1, fr)):
        for cc, wc in ((c0, 1 - fc), (c0 + 1, fc)):
            if wrap_cols:
                cc %= w
            if 0 <= rr < h and 0 <= cc < w:
                out += wr * wc * img[rr, cc]
    return out


def direct(img, out_hw, coord, wrap_cols=False):
    out = np.zeros(tuple(out_hw) + img.shape[2:])
    for a in range(out_hw[0]):
        for b in range(out_hw[1]):
            out[a, b] = bilinear(img, *coord(a, b), wrap_cols=wrap_cols)
    return out


def direct_polar(img, out_hw):
    return direct(img, out_hw, lambda i, j: safa_coord(i, j, img.shape[0], *out_hw))


def direct_ipt(img, out_hw):
    return direct(img, out_hw, lambda y, x: ipt_coord(y, x, *img.shape[:2], *out_hw), wrap_cols=True)


@pytest.fixture
def rng():
    return np.random.default_rng(0)


# ---- formula ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("s,out_hw", [(40, (8, 24)), (33, (10, 17))])
def test_polar_grid_matches_formula(s, out_hw):
    map_x, map_y = polar.aerial_to_polar_grid((s, s), out_hw)
    for i in range(out_hw[0]):
        for j in range(out_hw[1]):
            row, col = safa_coord(i, j, s, *out_hw)
            assert map_y[i, j] == pytest.approx(row, abs=1e-4)
            assert map_x[i, j] == pytest.approx(col, abs=1e-4)


@pytest.mark.parametrize("in_hw,out_hw", [((12, 48), (20, 20)), ((9, 31), (14, 18))])
def test_ipt_grid_matches_formula(in_hw, out_hw):
    map_x, map_y = polar.street_to_aerial_grid(in_hw, out_hw)
    for y in range(out_hw[0]):
        for x in range(out_hw[1]):
            row, col = ipt_coord(y, x, *in_hw, *out_hw)
            assert map_y[y, x] == pytest.approx(row, abs=1e-4)
            assert map_x[y, x] == pytest.approx(col, abs=1e-3)
            assert 0 <= map_x[y, x] <= in_hw[1]


def test_polar_image_matches_direct_evaluation(rng):
    img = rng.integers(0, 256, (40, 40, 3), dtype=np.uint8)
    out = aerial_to_polar(img, (10, 30))
    ref = direct_polar(img.astype(np.float64), (10, 30))
    assert np.abs(out - ref).max() <= REMAP_TOL
    assert np.abs(out - ref).mean() < 1.5
    assert out.dtype == np.uint8


def test_ipt_image_matches_direct_evaluation(rng):
    img = rng.integers(0, 256, (12, 48, 3), dtype=np.uint8)
    out = street_to_aerial(img, (24, 24))
    ref = direct_ipt(img.astype(np.float64), (24, 24))
    assert np.abs(out - ref).max() <= REMAP_TOL
    assert np.abs(out - ref).mean() < 1.5


def test_ipt_wraps_columns_without_seam():
    # A panorama that is constant except across the south seam (last and first columns): with wrapping, the
    # output just south of the centre interpolates between two equal values and never drops towards 0.
    img = np.full((16, 64), 200, np.uint8)
    out = street_to_aerial(img, (32, 32))
    map_x, map_y = polar.street_to_aerial_grid((16, 64), (32, 32))
    inside = map_y >= 0
    assert (map_x[inside] > 63).any()  # the seam is actually sampled
    assert np.all(out[inside] == 200)
    assert np.all(out[map_y <= -1] == 0)  # corners beyond the top row are 0


def test_round_trip_reproduces_panorama():
    """docs/conventions.md "IPT": sampling the IPT output back along the same rays reproduces the panorama."""
    h_s, w_s, h_a, w_a = 224, 1232, 288, 288
    rows, cols = np.mgrid[0:h_s, 0:w_s].astype(np.float64)
    pano = 128 + 60 * np.sin(2 * np.pi * 2 * cols / w_s) + 50 * np.cos(np.pi * rows / h_s)
    pano = np.clip(np.rint(pano), 0, 255).astype(np.uint8)
    aerial = street_to_aerial(pano, (h_a, w_a))

    y = (h_s - 1) - rows  # rows above the bottom row
    rho = y * h_a / (math.sqrt(2) * h_s)
    theta = 2 * np.pi * cols / w_s
    back_row = h_a / 2 + rho * np.cos(theta)
    back_col = w_a / 2 - rho * np.sin(theta)
    back = cv2.remap(aerial.astype(np.float32), back_col.astype(np.float32), back_row.astype(np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    inside = (back_row >= 0) & (back_row <= h_a - 1) & (back_col >= 0) & (back_col <= w_a - 1)
    # Leave out what no grid can hold: the top row (it blends with the zeros beyond the corners) and the rows
    # within 8 px of the camera, where a whole turn of the panorama falls on a few output pixels.
    inside &= (rows >= 1) & (y >= 8)
    assert inside.mean() > 0.6
    err = np.abs(back - pano)[inside]
    assert err.max() <= 2
    assert err.mean() < 0.5
    # A wrong angle convention fails loudly: the same check with the columns mirrored is far off.
    mirrored = cv2.remap(aerial.astype(np.float32), (w_a - back_col).astype(np.float32),
                         back_row.astype(np.float32), cv2.INTER_LINEAR)
    assert np.abs(mirrored - pano)[inside].max() > 50


# ---- orientation -----------------------------------------------------------------------------------------------
def _red_column(out):
    redness = out[..., 0].astype(int) - out[..., 1].astype(int)
    return np.unravel_index(np.argmax(redness), redness.shape)


@pytest.mark.parametrize("where,expected_fraction", [
    ("north", 0.5), ("east", 0.75), ("south", 0.0), ("west", 0.25)])
def test_polar_mark_placement(where, expected_fraction):
    s, (h, w) = 100, (32, 64)
    img = np.zeros((s, s, 3), np.uint8)
    c = s // 2
    row, col = {"north": (c - 30, c), "south": (c + 30, c), "east": (c, c + 30), "west": (c, c - 30)}[where]
    img[row - 3:row + 4, col - 3:col + 4] = (255, 0, 0)
    out = aerial_to_polar(img, (h, w))
    _, j = _red_column(out)
    expected = expected_fraction * w
    assert min(abs(j - expected), w - abs(j - expected)) <= 1


def test_polar_centre_is_bottom_row_and_edge_is_top_row():
    s = 64
    img = np.zeros((s, s), np.uint8)
    img[s // 2 - 2:s // 2 + 3, s // 2 - 2:s // 2 + 3] = 255
    out = aerial_to_polar(img, (16, 32))
    assert np.all(out[-1] == 255)
    assert np.all(out[0] == 0)


@pytest.mark.parametrize("col_fraction,side", [(0.5, "up"), (0.25, "left"), (0.75, "right"), (0.0, "down")])
def test_ipt_column_placement(col_fraction, side):
    h_s, w_s, n = 32, 128, 64
    pano = np.zeros((h_s, w_s, 3), np.uint8)
    c = int(col_fraction * w_s)
    for dc in range(-2, 3):
        pano[:, (c + dc) % w_s] = (255, 0, 0)
    out = street_to_aerial(pano, (n, n))
    ys, xs = np.nonzero(out[..., 0] > 128)
    dy, dx = ys.mean() - n / 2, xs.mean() - n / 2
    direction = {"up": (-1, 0), "down": (1, 0), "left": (0, -1), "right": (0, 1)}[side]
    along = dy * direction[0] + dx * direction[1]
    across = dy * direction[1] - dx * direction[0]
    assert along > n / 8
    assert abs(across) < 1.5


def test_ipt_camera_at_centre_sky_at_corners():
    pano = np.zeros((20, 80), np.uint8)
    pano[-1] = 255  # bottom row: the ground under the camera
    pano[0] = 100  # top row: the sky
    out = street_to_aerial(pano, (40, 40))
    assert out[20, 20] == 255
    assert out[0, 0] == 0  # beyond the top row
    map_x, map_y = polar.street_to_aerial_grid((20, 80), (40, 40))
    assert map_y.min() < 0 < map_y.max() == pytest.approx(19)


# ---- shapes, dtypes, cache, errors -----------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [(30, 30), (30, 30, 1), (30, 30, 3), (30, 30, 4)])
@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_channels_and_dtype_preserved(shape, dtype):
    img = (np.arange(np.prod(shape)) % 251).reshape(shape).astype(dtype)
    p = aerial_to_polar(img, (8, 16))
    a = street_to_aerial(img, (12, 10))
    assert p.shape == (8, 16) + shape[2:] and p.dtype == dtype
    assert a.shape == (12, 10) + shape[2:] and a.dtype == dtype


def test_grids_are_cached_and_read_only():
    polar.aerial_to_polar_grid.cache_clear()
    img = np.zeros((24, 24, 3), np.uint8)
    aerial_to_polar(img, (6, 12))
    aerial_to_polar(img, (6, 12))
    info = polar.aerial_to_polar_grid.cache_info()
    assert info.misses == 1 and info.hits == 1
    assert polar.aerial_to_polar_grid((24, 24), (6, 12))[0] is polar.aerial_to_polar_grid((24, 24), (6, 12))[0]
    map_x, _ = polar.street_to_aerial_grid((8, 16), (6, 6))
    with pytest.raises(ValueError):
        map_x[0, 0] = 1.0


def test_normalized_grid_matches_remap():
    torch = pytest.importorskip("torch")
    img = np.random.default_rng(1).random((10, 40)).astype(np.float32)
    map_x, map_y = polar.street_to_aerial_grid((10, 40), (16, 16))
    wrapped = np.concatenate([img, img[:, :1]], axis=1)
    grid = polar.normalized_grid(map_x, map_y, wrapped.shape)
    got = torch.nn.functional.grid_sample(torch.from_numpy(wrapped)[None, None], torch.from_numpy(grid)[None],
                                          mode="bilinear", padding_mode="zeros", align_corners=True)[0, 0]
    np.testing.assert_allclose(got.numpy(), street_to_aerial(img, (16, 16)), atol=0.05)


@pytest.mark.parametrize("fn,name", [(aerial_to_polar, "aerial image"), (street_to_aerial, "street image")])
@pytest.mark.parametrize("bad,err,match", [
    ([[1, 2], [3, 4]], TypeError, "must be a numpy array .* got list"),
    (np.zeros((2, 8, 8, 3), np.uint8), ValueError, r"must be HxW or HxWxC, got shape \(2, 8, 8, 3\)"),
    (np.zeros(8, np.uint8), ValueError, "must be HxW or HxWxC"),
    (np.zeros((8, 8, 3), np.int16), TypeError, "must be uint8 .* got dtype int16"),
    (np.zeros((8, 8, 3), np.float64), TypeError, "must be uint8 .* got dtype float64"),
    (np.zeros((0, 8, 3), np.uint8), ValueError, "is empty"),
    (np.zeros((8, 0, 3), np.uint8), ValueError, "is empty"),
    (np.zeros((8, 8, 0), np.uint8), ValueError, "is empty"),
])
def test_bad_images(fn, name, bad, err, match):
    with pytest.raises(err, match=f"{name} {match}"):
        fn(bad, (4, 4))


@pytest.mark.parametrize("fn", [aerial_to_polar, street_to_aerial])
@pytest.mark.parametrize("out_hw", [(0, 4), (4, 0), (4,), "ab", (4.5, 4), None])
def test_bad_out_hw(fn, out_hw):
    with pytest.raises(ValueError, match="out_hw must be a pair of positive ints"):
        fn(np.zeros((8, 8, 3), np.uint8), out_hw)


def test_one_pixel_sizes_are_valid():
    assert aerial_to_polar(np.full((1, 1), 7, np.uint8), (1, 1)).shape == (1, 1)
    assert street_to_aerial(np.full((1, 5), 7, np.uint8), (3, 1)).shape == (3, 1)
    assert street_to_aerial(np.full((5, 1, 3), 7, np.uint8), (1, 3)).shape == (1, 3, 3)


def test_normalized_grid_maps_pixel_centres_to_the_corners():
    # align_corners=True: pixel 0 is -1 and pixel size-1 is +1, down to a 2-pixel side
    grid = polar.normalized_grid(np.array([[0.0, 1.0]]), np.array([[0.0, 1.0]]), (2, 2))
    np.testing.assert_array_equal(grid, [[[-1, -1], [1, 1]]])
    grid = polar.normalized_grid(np.array([[0.0, 1.0]]), np.array([[0.0, 2.0]]), (3, 2))
    np.testing.assert_array_equal(grid, [[[-1, -1], [1, 1]]])
    with pytest.raises(ValueError, match="in_hw"):
        polar.normalized_grid(np.zeros((1, 1)), np.zeros((1, 1)), (0, 2))


def test_polar_needs_square_aerial():
    with pytest.raises(ValueError, match="square"):
        aerial_to_polar(np.zeros((8, 9, 3), np.uint8), (4, 4))


# ---- real samples (never copied into the repo) -----------------------------------------------------------------
@pytest.mark.skipif(not (REALDATA / "cvusa_mini").exists(), reason="no real CVUSA sample")
def test_real_cvusa_pair_both_ways():
    root = REALDATA / "cvusa_mini"
    row = (root / "splits" / "val-19zl.csv").read_text().splitlines()[0].split(",")
    aerial = cv2.imread(str(root / row[0]))
    street = cv2.imread(str(root / row[1]))
    assert aerial.shape == (750, 750, 3) and street.shape == (224, 1232, 3)

    p = aerial_to_polar(aerial, (112, 616))
    assert p.shape == (112, 616, 3) and p.dtype == np.uint8
    assert p.max() <= aerial.max() and p.std() > 10  # real content, not a blank frame
    centre = aerial[374:377, 374:377].reshape(-1, 3).astype(float)
    assert np.abs(p[-1].astype(float).mean(0) - centre.mean(0)).max() < 20  # bottom row = aerial centre

    a = street_to_aerial(street, (288, 288))
    assert a.shape == (288, 288, 3) and a.dtype == np.uint8
    assert a.max() <= street.max() and a.std() > 10
    assert np.all(a[0, 0] == 0)  # the far corner lies beyond the top row


@pytest.mark.skipif(not (REALDATA / "cvact_mini").exists(), reason="no real CVACT sample")
def test_real_cvact_pair_both_ways():
    root = REALDATA / "cvact_mini" / "ANU_data_small"
    aerial = cv2.imread(str(next((root / "satview_polish").glob("*_satView_polish.jpg"))))
    street = cv2.imread(str(next((root / "streetview").glob("*_grdView.jpg"))))[208:624]  # SAFA's horizon band
    assert aerial_to_polar(aerial, (112, 616)).shape == (112, 616, 3)
    assert street_to_aerial(street, (288, 288)).shape == (288, 288, 3)
