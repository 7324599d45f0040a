"""Alignment transforms between the aerial and the street view, as cached ``cv2.remap`` grids.

- ``aerial_to_polar``: SAFA's polar transform (Shi et al., NeurIPS 2019), aerial S x S -> street-like H x W.
- ``street_to_aerial``: the inverse polar transform (IPT) of Li et al., "Multi-scale attention encoder for
  street-to-aerial image geo-localization" (CAAI TIT 2023), eq. 1-2: panorama -> aerial-like image.
- ``street_to_ground``: the ground-plane projection of a full sphere's horizon band: an aerial-like image in
  metres, as a flat-ground camera of known height sees it (``dataset.alignment=ground``).

Both share one angle convention, the one of CVUSA panoramas: column 0 looks south, the centre column north, and
the columns turn clockwise seen from above (south, west, north, east). North is up in aerial images.

The sampling grids depend only on (input shape, output shape) (and the ground projection's metres), so they are
built once and cached; a transform is then one ``cv2.remap`` call. The grid builders are public so that a torch
pipeline can reuse them (``normalized_grid`` converts a grid for ``torch.nn.functional.grid_sample``).
"""
from __future__ import annotations

import functools
import math

import cv2
import numpy as np

__all__ = [
    "aerial_to_polar",
    "street_to_aerial",
    "street_to_ground",
    "aerial_to_polar_grid",
    "street_to_aerial_grid",
    "street_to_ground_grid",
    "normalized_grid",
]

_DTYPES = (np.uint8, np.float32)


def _check_hw(hw, name: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in hw)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair of positive ints (height, width), got {hw!r}") from None
    if h <= 0 or w <= 0 or (h, w) != tuple(hw):
        raise ValueError(f"{name} must be a pair of positive ints (height, width), got {hw!r}")
    return h, w


def _check_image(img, name: str) -> np.ndarray:
    if not isinstance(img, np.ndarray):
        raise TypeError(f"{name} must be a numpy array (HxW or HxWxC), got {type(img).__name__}")
    if img.ndim not in (2, 3):
        raise ValueError(f"{name} must be HxW or HxWxC, got shape {img.shape}")
    if img.dtype not in _DTYPES:
        raise TypeError(f"{name} must be uint8 (or float32), got dtype {img.dtype}")
    if img.shape[0] == 0 or img.shape[1] == 0 or (img.ndim == 3 and img.shape[2] == 0):
        raise ValueError(f"{name} is empty: shape {img.shape}")
    return img


def _freeze(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    # The grids are shared through the cache: make accidental in-place edits fail loudly.
    for a in arrays:
        a.setflags(write=False)
    return arrays


@functools.lru_cache(maxsize=32)
def aerial_to_polar_grid(in_hw: tuple[int, int], out_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """SAFA polar grid: for output pixel (i, j), the aerial (col, row) it samples.

    With S the aerial size and (H, W) = out_hw, r = (S/2)/H * (H-1-i):
    row = S/2 + r cos(2πj/W), col = S/2 - r sin(2πj/W). The top row is the outer radius, the bottom row the
    centre; j = 0 looks south, j = W/2 north. Returns (map_x, map_y), float32 H x W each, pixel units, read-only.
    """
    s_h, s_w = _check_hw(in_hw, "aerial shape")
    if s_h != s_w:
        raise ValueError(f"aerial_to_polar needs a square aerial image (S x S), got {s_h}x{s_w}")
    h, w = _check_hw(out_hw, "out_hw")
    s = float(s_h)
    i = np.arange(h, dtype=np.float64)[:, None]
    j = np.arange(w, dtype=np.float64)[None, :]
    r = (s / 2) / h * (h - 1 - i)
    theta = 2 * np.pi * j / w
    map_y = (s / 2 + r * np.cos(theta)).astype(np.float32)
    map_x = (s / 2 - r * np.sin(theta)).astype(np.float32)
    return _freeze(map_x, map_y)


@functools.lru_cache(maxsize=32)
def street_to_aerial_grid(in_hw: tuple[int, int], out_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """IPT grid: for aerial-like output pixel (y, x), the panorama (col, row) it samples.

    With (H_s, W_s) = in_hw and (H_a, W_a) = out_hw: r = sqrt((x - W_a/2)^2 + (y - H_a/2)^2) reads the street
    row sqrt(2) * (H_s/H_a) * r rows above the bottom row, and the angle phi reads column W_s * phi / (2π), with
    phi measured like SAFA's angle (phi = 0 south, π north, clockwise from above). Columns lie in [0, W_s):
    values past W_s - 1 interpolate between the last and the first column (the panorama wraps), which
    ``street_to_aerial`` implements by appending the first column. Returns (map_x, map_y), float32, read-only.
    """
    h_s, w_s = _check_hw(in_hw, "street shape")
    h_a, w_a = _check_hw(out_hw, "out_hw")
    y = np.arange(h_a, dtype=np.float64)[:, None] - h_a / 2
    x = np.arange(w_a, dtype=np.float64)[None, :] - w_a / 2
    r = np.sqrt(x * x + y * y)
    # The paper writes y_s = sqrt(2) * (H_s/H_a) * r as if it grew from the *top* row, which would put the camera
    # at the sky. We implement the geometric reading: r = 0 (the camera) is the bottom row of the panorama
    # (the ground under the car) and the corners of the aerial-like image reach the top row.
    map_y = (h_s - 1) - math.sqrt(2) * (h_s / h_a) * r
    # Inverse of SAFA's (row, col) = (c + r cos(phi), c - r sin(phi)): cos(phi) = y/r, sin(phi) = -x/r.
    phi = np.mod(np.arctan2(-x, y), 2 * np.pi)
    map_x = w_s * phi / (2 * np.pi)
    map_x = np.broadcast_to(map_x, (h_a, w_a)).astype(np.float32)
    return _freeze(map_x, map_y.astype(np.float32))


def normalized_grid(map_x: np.ndarray, map_y: np.ndarray, in_hw: tuple[int, int]) -> np.ndarray:
    """Pixel grid -> H x W x 2 (x, y) in [-1, 1], for ``grid_sample(..., align_corners=True)``.

    ``grid_sample`` pads with zeros (``padding_mode="zeros"``) like ``cv2.BORDER_CONSTANT``; for the IPT grid,
    append the first column to the panorama first and pass ``in_hw = (H_s, W_s + 1)`` to get the wrap.
    """
    h, w = _check_hw(in_hw, "in_hw")
    gx = 2 * map_x / max(w - 1, 1) - 1
    gy = 2 * map_y / max(h - 1, 1) - 1
    return np.stack([gx, gy], axis=-1).astype(np.float32)


def _remap(img: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    out = cv2.remap(img, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=0)
    if img.ndim == 3 and out.ndim == 2:  # cv2 drops a trailing channel axis of size 1
        out = out[:, :, None]
    return out


def aerial_to_polar(img: np.ndarray, out_hw: tuple[int, int] = (112, 616)) -> np.ndarray:
    """SAFA polar transform of an S x S (x C) aerial image to an ``out_hw`` street-like image.

    Bilinear sampling; samples outside the aerial image are 0. Same channels and dtype as the input.
    """
    img = _check_image(img, "aerial image")
    map_x, map_y = aerial_to_polar_grid(tuple(img.shape[:2]), _check_hw(out_hw, "out_hw"))
    return _remap(img, map_x, map_y)


def street_to_aerial(img: np.ndarray, out_hw: tuple[int, int] = (288, 288), wrapped: bool = False) -> np.ndarray:
    """Inverse polar transform (IPT) of an H_s x W_s (x C) panorama to an ``out_hw`` aerial-like image.

    Bilinear sampling; the panorama's columns wrap (no seam at south), rows outside it give 0 (the corners).
    Same channels and dtype as the input. wrapped: ``img`` already ends with a copy of its first column
    (H_s x (W_s + 1), e.g. a window of a panorama laid twice side by side), so the copy that appends it is skipped.
    """
    out_hw = _check_hw(out_hw, "out_hw")
    return _remap_wrapping(img, wrapped, lambda in_hw: street_to_aerial_grid(in_hw, out_hw))


def _remap_wrapping(img: np.ndarray, wrapped: bool, grid) -> np.ndarray:
    """Sample a street image whose columns wrap with `grid(in_hw)` -> (map_x, map_y): the first column is appended
    (unless `wrapped`: the image already ends with its copy), so values past W - 1 interpolate towards column 0."""
    img = _check_image(img, "street image")
    if wrapped and img.shape[1] < 2:
        raise ValueError(f"a wrapped street image ends with a copy of its first column, so it has >= 2 columns; "
                         f"got shape {img.shape}")
    in_hw = (img.shape[0], img.shape[1] - 1) if wrapped else tuple(img.shape[:2])
    map_x, map_y = grid(in_hw)
    return _remap(img if wrapped else np.concatenate([img, img[:, :1]], axis=1), map_x, map_y)


# The ground-plane projection. The IPT maps panorama rows to radius linearly, so on a 73 m VIGOR tile the ground from
# about 12 m to the tile's edge, most of the tile, falls on a thin ring at the horizon circle. This projection puts each
# ground point where it lies: aerial-like pixel (y, x) covers the point e metres east and n north of the camera (pixel
# centres, extent_m metres across the image, north up), which a camera h metres high sees at bearing atan2(e, n) and
# elevation -atan(h / d), d = hypot(e, n). What stands on the ground (walls, trees) is smeared outward from its foot;
# the sky and everything above the camera are not used. The street image is the horizon band of a full-sphere
# panorama (rows H/4 to 3H/4, elevations +45° to -45°, as transforms.horizon_band cuts it), with the IPT's columns.
# Ground nearer than h (below -45°) is outside the band and 0.
BAND_DEG = 45.0  # the horizon band spans elevations +BAND_DEG (top row) to -BAND_DEG (bottom row)


@functools.lru_cache(maxsize=32)
def street_to_ground_grid(in_hw: tuple[int, int], out_hw: tuple[int, int], extent_m: float,
                          camera_height_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For aerial-like output pixel (y, x), the band's (col, row) it samples -> (map_x, map_y), float32, read-only.

    Row r of an H-row band has its centre at elevation BAND_DEG - (r + 0.5)·2·BAND_DEG/H; columns as
    street_to_aerial's (values past W - 1 interpolate towards column 0: street_to_ground appends it)."""
    h_s, w_s = _check_hw(in_hw, "street shape")
    h_a, w_a = _check_hw(out_hw, "out_hw")
    if not (math.isfinite(extent_m) and extent_m > 0 and math.isfinite(camera_height_m) and camera_height_m > 0):
        raise ValueError(f"the ground projection needs extent_m > 0 and camera_height_m > 0, got {extent_m!r} and "
                         f"{camera_height_m!r}")
    east = (np.arange(w_a, dtype=np.float64)[None, :] + 0.5 - w_a / 2) * (extent_m / w_a)
    north = -(np.arange(h_a, dtype=np.float64)[:, None] + 0.5 - h_a / 2) * (extent_m / h_a)
    bearing = np.degrees(np.arctan2(east, north))  # clockwise from north
    elevation = -np.degrees(np.arctan2(camera_height_m, np.hypot(east, north)))
    map_x = np.mod(bearing - 180.0, 360.0) / 360.0 * w_s
    map_y = (BAND_DEG - elevation) / (2 * BAND_DEG) * h_s - 0.5
    return _freeze(map_x.astype(np.float32), map_y.astype(np.float32))


def street_to_ground(img: np.ndarray, out_hw: tuple[int, int], extent_m: float, camera_height_m: float,
                     wrapped: bool = False) -> np.ndarray:
    """The ground-plane projection of a horizon band (H x W (x C), uint8 or float32) to `out_hw`, covering
    `extent_m` metres, seen from `camera_height_m` metres. Bilinear; the columns wrap. wrapped: `img` already ends
    with a copy of its first column (as in street_to_aerial)."""
    out_hw, extent_m, camera_height_m = _check_hw(out_hw, "out_hw"), float(extent_m), float(camera_height_m)
    return _remap_wrapping(img, wrapped, lambda in_hw: street_to_ground_grid(in_hw, out_hw, extent_m, camera_height_m))
