"""One query's settings and what it may cost, checked the same way for localize.py and `geoloc serve`.

A query's work grows with:
- the decoded pixels, W×H;
- the 360° canvas the view is placed on (geoloc/tasks/crossview/views.py): W·360/fov columns by H rows, so a 1°
  photo makes a canvas 360 times its width, and OpenCV's remap (the IPT) takes fewer than 32,767 of either;
- the candidate headings searched when the heading is unknown (heading_steps), one query-branch pass each.
Each has a limit (QueryLimits). The settings are parsed once, at the door (localize.py's keys, the service's form),
by `check_settings` into a QuerySettings that everything below trusts, topk held to max_topk there; `check_headings`
holds heading_steps to max_headings when a localizer is loaded. `check_size` (through a Localizer's `check`) runs on
an image's header, which `image_size` reads, before anything is decoded or allocated, and on the array the
localizer is given: decoding may turn an image (its EXIF orientation), and a caller's array has no header. Past a
limit, or on a bad setting, QueryError names the key, the value, the limit and what to do.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, fields
from typing import Any

from PIL import Image, UnidentifiedImageError

SEARCH = "search"  # heading=search: the heading is searched whatever the checkpoint was trained on
OPENCV_SIDE = 32_766  # cv2.remap takes fewer than 32,767 rows and columns; the IPT appends one wrap column

FOV = "the horizontal field of view in degrees, in (0, 360]: 360 for a full panorama (the default)"
TOPK = "how many references to return, an integer from 1 to max_topk (default 5)"
HEADING = ("the image's bearing in degrees clockwise from north, when known (0 for a north-aligned panorama); "
           "'search' to have it searched over candidate headings; left out: as the checkpoint was trained "
           "(searched when it was trained with an unknown heading, else north, 0)")
HEADING_PRIOR = ("how far, in degrees, the true bearing may lie from the given heading, in [0, 180]: the heading "
                 "search then tries only the candidate headings within heading ± heading_prior (needs heading)")
ABSTAIN = ("a confidence threshold in [0, 1]: an answer whose confidence (the calibrated probability that its top-1 "
           "tile is right) is below it says it abstains; needs a calibrated gallery and a given heading")
REFINE = ("whether each top-k tile's position is refined inside the tile, where the checkpoint has a refiner and "
          "the image is a panorama: true (the default) or false, for a faster answer with the tiles' own positions")
HINTS = {"fov": FOV, "topk": TOPK, "heading": HEADING, "heading_prior": HEADING_PRIOR, "abstain": ABSTAIN,
         "refine": REFINE}


@dataclass
class QuerySettings:
    """A query's settings, as localize.py's keys and the service's form fields take them, with their defaults."""

    fov: float = 360.0  # the image's horizontal field of view in degrees: 360 = a panorama; less = a street photo
    topk: int = 5  # references returned
    # its bearing when known (degrees clockwise from north; CVUSA panoramas: 0), "search", or None: as the checkpoint
    # was trained (Localizer.settings: searched when trained with an unknown heading, else 0)
    heading: Any = None
    heading_prior: float | None = None  # ± degrees around `heading` the search tries; None: heading taken as exact
    abstain: float | None = None  # answers less confident than this abstain; None: never
    refine: bool = True  # refine the top-k positions where the checkpoint can (Localizer.settings: whether it does)


SETTINGS = tuple(f.name for f in fields(QuerySettings))  # the settings' keys, as localize.py and the form take them


@dataclass
class QueryLimits:
    """What one query may cost (keys of localize.py and `geoloc serve`). The defaults keep one query of the default
    model under ~300 MB above the model and gallery and under ~10 s on a 2-core CPU (benchmarks/README.md)."""

    max_pixels: int = 25_000_000  # decoded W×H, and the canvas's rows × columns; a 7,072 x 3,536 panorama
    max_canvas_side: int = 16_384  # the canvas's columns (W·360/fov) and rows (H); at most 32,766 (OpenCV's remap)
    max_headings: int = 72  # candidate headings a query with no heading is encoded at (heading_steps): every 5°
    max_topk: int = 100  # references one answer lists

    def __post_init__(self):
        for key in ("max_pixels", "max_canvas_side", "max_headings", "max_topk"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} must be >= 1, got {getattr(self, key)}")
        if self.max_canvas_side > OPENCV_SIDE:
            raise ValueError(f"max_canvas_side={self.max_canvas_side} is over {OPENCV_SIDE:,}, the most columns "
                             "OpenCV's remap (the inverse polar transform) takes")

    def limits(self) -> QueryLimits:
        """These limits alone (a config that extends QueryLimits gives its limit keys)."""
        return QueryLimits(self.max_pixels, self.max_canvas_side, self.max_headings, self.max_topk)


class QueryError(ValueError):
    """A bad setting (status 422) or a query over a limit (413), or an unreadable image (400, 415). `key` names the
    setting or the limit; the message says what is wrong and what to do."""

    def __init__(self, key: str, message: str, status: int = 422):
        super().__init__(message)
        self.key, self.status = key, status


def _bad(key: str, value, problem: str) -> QueryError:
    return QueryError(key, f"{key}={value!r} {problem} ({HINTS[key]})")


def _number(key: str, value) -> float:
    if isinstance(value, bool):
        raise _bad(key, value, "is not a number")
    try:
        number = float(value.strip() if isinstance(value, str) else value)
    except (TypeError, ValueError):
        raise _bad(key, value, "is not a number") from None
    if not math.isfinite(number):
        raise _bad(key, value, "is not a finite number")
    return number


def _flag(key: str, value) -> bool:
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text not in ("true", "false", "1", "0", "yes", "no"):
        raise _bad(key, value, "is not true or false")
    return text in ("true", "1", "yes")


def check_settings(fov: Any = None, topk: Any = None, heading: Any = None, max_topk: int | None = None,
                   heading_prior: Any = None, abstain: Any = None, refine: Any = None) -> QuerySettings:
    """Settings as given (numbers, or text as a form sends them; None: the default) -> QuerySettings, or QueryError
    naming the setting; topk is held to max_topk when it is given (413)."""
    default = QuerySettings()
    number = default.fov if fov is None else _number("fov", fov)
    if not 0.0 < number <= 360.0:
        raise _bad("fov", fov, "is outside (0, 360]")
    fov = number
    if topk is None:
        topk = default.topk
    else:
        number = _number("topk", topk)
        if number != int(number) or (isinstance(topk, str) and not topk.strip().lstrip("+").isdigit()):
            raise _bad("topk", topk, "is not an integer")
        if number < 1:
            raise _bad("topk", topk, "is below 1")
        topk = int(number)
    if max_topk is not None and topk > max_topk:
        raise QueryError("max_topk", f"topk={topk} is over the limit of {max_topk} references an answer lists "
                                     "(max_topk): ask for fewer", 413)
    if heading is None or heading == "":
        heading = default.heading
    elif isinstance(heading, str) and heading.strip().lower() == SEARCH:
        heading = SEARCH
    else:
        heading = _number("heading", heading)
    prior = None if heading_prior is None or heading_prior == "" else _number("heading_prior", heading_prior)
    if prior is not None:
        if not 0.0 <= prior <= 180.0:
            raise _bad("heading_prior", heading_prior, "is outside [0, 180]")
        if heading is None or heading == SEARCH:
            raise _bad("heading_prior", heading_prior, "is given without heading: give the heading it is around")
    threshold = None if abstain is None or abstain == "" else _number("abstain", abstain)
    if threshold is not None and not 0.0 <= threshold <= 1.0:
        raise _bad("abstain", abstain, "is outside [0, 1]")
    refine = default.refine if refine is None or refine == "" else _flag("refine", refine)
    return QuerySettings(fov, topk, heading, prior, threshold, refine)


def check_headings(steps: int, limits: QueryLimits) -> int:
    """The candidate headings of a search (heading_steps), within max_headings."""
    if int(steps) != steps or steps < 1:
        raise QueryError("heading_steps", f"heading_steps must be an integer >= 1, got {steps!r}")
    if steps > limits.max_headings:
        raise QueryError("max_headings", f"heading_steps={steps} candidate headings is over max_headings="
                                         f"{limits.max_headings} (each is one pass of the query branch): give "
                                         f"heading_steps={limits.max_headings} or fewer, or raise max_headings", 413)
    return int(steps)


def check_size(name: str, width: int, height: int, fov: float, canvas: tuple[int, float],
               limits: QueryLimits) -> None:
    """QueryError (413) naming the limit when the W×H image `name`, or the (rows, columns) canvas a view of `fov`
    degrees is placed on, is over `limits`; columns may be inf (a vanishing fov)."""
    rows, columns = canvas
    if rows < 1:  # a full sphere keeps rows H/4 to 3H/4: none of a 1-row image
        raise QueryError("image", f"{name} is {width}x{height}: the street view cut from it has no rows (a full-sphere "
                                  "panorama, as this gallery's queries are, keeps its horizon band, rows H/4 to "
                                  "3H/4): give the whole panorama, at least 2 rows high")
    if width * height > limits.max_pixels:
        raise QueryError("max_pixels", f"{name} is {width}x{height} = {width * height:,} pixels, over the "
                                       f"limit of {limits.max_pixels:,} (max_pixels): downscale it (the network sees "
                                       "a few hundred pixels across) and send it again", 413)
    if rows > limits.max_canvas_side:
        raise QueryError("max_canvas_side", f"{name} is {rows:,} rows high, over the limit of "
                                            f"{limits.max_canvas_side:,} (max_canvas_side): downscale it", 413)
    columns = round(columns) if columns < 1e12 else columns  # inf for a vanishing fov
    shown = f"{columns:,}" if columns < 1e12 else f"{columns:.3g}"
    view = (f"{name}, a fov={fov:g} view {width:,} columns wide, is placed on a 360° canvas of {shown} columns "
            "(W·360/fov)")
    if columns > limits.max_canvas_side:
        most = math.floor(limits.max_canvas_side * fov / 360.0)
        smaller = f", or downscale it to at most {most:,} columns" if most >= 1 else ""
        raise QueryError("max_canvas_side", f"{view}, over the limit of {limits.max_canvas_side:,} "
                                            f"(max_canvas_side): give the image's true fov{smaller}", 413)
    if rows * columns > limits.max_pixels:
        raise QueryError("max_pixels", f"{view} and {rows:,} rows: {rows * columns:,} pixels, over the limit of "
                                       f"{limits.max_pixels:,} (max_pixels): downscale the image", 413)


def image_size(data: bytes, name: str) -> tuple[int, int, str]:
    """(width, height, format) of image bytes from their header alone (PIL parses the header lazily), so that a
    decompression bomb is measured unread; QueryError 400 (empty) or 415 (not an image)."""
    if not data:
        raise QueryError("image", f"{name} is empty (0 bytes)", 400)
    try:
        with Image.open(io.BytesIO(data)) as header:
            return (*header.size, header.format)
    except Image.DecompressionBombError as err:  # PIL's own guard, far above max_pixels
        raise QueryError("max_pixels", f"{name} is too large: {err}. Downscale it", 413) from None
    except (UnidentifiedImageError, SyntaxError, ValueError, OSError):  # what PIL raises on a header it cannot read
        raise QueryError("image", f"{name} is not an image (it starts with {data[:16]!r}): give a JPEG or PNG",
                         415) from None
