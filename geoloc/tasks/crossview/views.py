"""Street views of unknown heading and limited field of view on the 360° canvas (DSM, Shi et al.,
"Where am I looking at? Joint location and orientation estimation by cross-view matching", CVPR 2020).

Bearings follow docs/conventions.md "Panorama bearings": column j of a W-wide north-aligned panorama looks along
bearing 180° + 360°·j/W (south at column 0, north at the centre column, clockwise seen from above). A view of
heading h (the bearing of its centre column) and field of view f, W' columns wide, shows the bearings
[h - f/2, h + f/2): its column i looks along h - f/2 + f·i/W'. A 360° view of heading 0 is the north-aligned
panorama itself.

On the canvas the view sits at its bearings and everything else is 0. After the alignment (IPT, polar), a change
of heading is a rotation / circular shift, so trying K candidate headings is a circular correlation through the
query encoder (geoloc/tasks/crossview/heading.py scores it).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from geoloc.config import ConfigError


def check_fov(fov_deg: float, where: str = "fov_deg") -> float:
    fov = float(fov_deg)
    if not 0.0 < fov <= 360.0:
        raise ConfigError(f"{where} must lie in (0, 360] degrees, got {fov_deg!r}")
    return fov


def _check_image(img, name: str) -> np.ndarray:
    if not isinstance(img, np.ndarray) or img.ndim not in (2, 3) or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"{name} must be a non-empty HxW or HxWxC numpy array, got "
                         f"{getattr(img, 'shape', type(img).__name__)}")
    return img


def _view_columns(canvas_width: int, view_width: int, fov_deg: float, heading_deg: float) -> np.ndarray:
    """(view_width,) the canvas column of each view column: view column i looks along h - f/2 + f·i/W', which is
    canvas column (h - f/2 + 180)·W/360 + i (mod W), the offset rounded to a whole column."""
    offset = int(round((heading_deg - fov_deg / 2 + 180.0) * canvas_width / 360.0))
    return (offset + np.arange(view_width)) % canvas_width


def canvas_columns(view_width: int, fov_deg: float) -> float:
    """W'·360/f: the columns of the 360° canvas a W'-wide view of fov f degrees sits on, before rounding (inf when
    f is vanishingly small), so that a caller can refuse a canvas before it is allocated."""
    return view_width * 360.0 / check_fov(fov_deg)


def view_canvas(street: np.ndarray, fov_deg: float, heading_deg: float) -> np.ndarray:
    """street: H×W'×C covering fov_deg of bearing centred on heading_deg → H×W×C 360° canvas,
    W = round(W'·360/f), the view at its bearings and zeros elsewhere (fov 360: a circular roll of the view)."""
    street = _check_image(street, "street view")
    fov = check_fov(fov_deg)
    view_width = street.shape[1]
    width = round(canvas_columns(view_width, fov))  # >= view_width, as 360 / fov >= 1
    canvas = np.zeros((street.shape[0], width, *street.shape[2:]), dtype=street.dtype)
    # the view's columns are one run from its first column, wrapping once at the canvas's end: two slice copies
    # (a fancy-indexed scatter of the same columns takes 20-30 times as long on a large panorama)
    start = int(_view_columns(width, 1, fov, heading_deg)[0])
    first = min(view_width, width - start)
    canvas[:, start:start + first] = street[:, :first]
    canvas[:, : view_width - first] = street[:, first:]
    return canvas


def view_canvases(street: np.ndarray, fov_deg: float, headings) -> Iterator[np.ndarray]:
    """view_canvas(street, fov_deg, h) for each h in headings, each with its first column appended (H×(W+1)×C, the
    wrap polar.street_to_aerial needs): read-only windows of one canvas laid twice side by side. Every canvas is a
    circular roll of one, so a heading search costs one canvas of 2W columns, not a canvas and its copy per
    heading (memory as one canvas and its wrapped copy; time independent of the number of headings)."""
    street = _check_image(street, "street view")
    fov = check_fov(fov_deg)
    view_width = street.shape[1]
    width = round(canvas_columns(view_width, fov))
    doubled = np.zeros((street.shape[0], 2 * width, *street.shape[2:]), dtype=street.dtype)
    doubled[:, :view_width] = street  # the view at offset 0 ...
    doubled[:, width:width + view_width] = street  # ... and again one canvas further
    doubled.setflags(write=False)
    for heading in headings:
        # the canvas of `heading` holds the view from column `offset`: column j is doubled's (j - offset) mod W
        start = -int(_view_columns(width, 1, fov, heading)[0]) % width
        yield doubled[:, start:start + width + 1]


def crop_view(panorama: np.ndarray, fov_deg: float, heading_deg: float) -> np.ndarray:
    """What a camera of heading heading_deg and field of view fov_deg sees of a north-aligned H×W×C panorama:
    H×W'×C, W' = max(1, round(W·f/360)); the inverse of view_canvas."""
    panorama = _check_image(panorama, "panorama")
    fov = check_fov(fov_deg)
    width = panorama.shape[1]
    view_width = max(1, min(width, int(round(width * fov / 360.0))))
    return np.ascontiguousarray(panorama[:, _view_columns(width, view_width, fov, heading_deg)])


def north_window(panorama: np.ndarray, fov_deg: float, heading_deg: float) -> np.ndarray:
    """The north-aligned panorama with only the columns a view of (heading, fov) sees kept, the rest 0: the
    canvas of crop_view at its true heading, at the panorama's own width (what training with a known or
    sampled heading feeds the query branch). fov 360 returns the panorama itself."""
    fov = check_fov(fov_deg)
    if fov == 360.0:
        return panorama
    width = panorama.shape[1]
    view_width = max(1, min(width, int(round(width * fov / 360.0))))
    out = np.zeros_like(panorama)
    columns = _view_columns(width, view_width, fov, heading_deg)
    out[:, columns] = panorama[:, columns]
    return out


def candidate_headings(steps: int) -> np.ndarray:
    """(steps,) headings 360·k/steps degrees, k = 0..steps-1."""
    if int(steps) != steps or steps < 1:
        raise ConfigError(f"heading_steps must be an int >= 1, got {steps!r}")
    return 360.0 * np.arange(int(steps)) / int(steps)


def headings_around(heading: float, prior: float, steps: int) -> np.ndarray:
    """The candidate headings of a search with a prior: heading + 360·k/steps for every integer k with
    |360·k/steps| <= prior, in [0, 360), the given heading first. prior 0 (or below one step): the heading alone."""
    step = 360.0 / candidate_headings(steps).shape[0]
    reach = int(np.floor(prior / step + 1e-9))
    offsets = sorted(range(-reach, reach + 1), key=lambda k: (abs(k), k))
    return np.mod(float(heading) + step * np.array(offsets, np.float64), 360.0)


def circular_error_deg(estimate, truth) -> np.ndarray:
    """|estimate - truth| on the circle, in [0, 180] degrees (elementwise)."""
    diff = np.mod(np.asarray(estimate, dtype=np.float64) - np.asarray(truth, dtype=np.float64), 360.0)
    return np.minimum(diff, 360.0 - diff)


EVAL_HEADING_SEED = 12  # the evaluation headings are one fixed draw, the same for every checkpoint


def eval_heading(index: int) -> float:
    """The true heading of evaluation query `index` under dataset.random_heading: U[0, 360) degrees drawn from
    numpy's default_rng((EVAL_HEADING_SEED, index)), so every run and checkpoint meets the same headings."""
    return float(np.random.default_rng((EVAL_HEADING_SEED, int(index))).uniform(0.0, 360.0))
