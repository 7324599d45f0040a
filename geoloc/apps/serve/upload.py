"""An uploaded file -> an H×W×3 uint8 RGB image, or a QueryError saying what is wrong and what to do.

The size is read from the header (geoloc.apps.query.image_size: PIL parses the header only) and checked
against the localizer's limits before anything is decoded, so a decompression bomb, or an image whose canvas at the
asked fov would be too large, is refused unread. Then the bytes are decoded strictly, as the dataset readers decode
them (geoloc.data.validate.decode_rgb): a truncated JPEG, a scan cut short with an end marker appended, or a header
promising more pixels than the data holds is refused, not filled with grey.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numpy as np

from geoloc.apps.query import QueryError, image_size
from geoloc.data.validate import DatasetFileError, decode_rgb

# what to tell a client that sent something unusable
SEND = "send the street image as the multipart/form-data file field 'image' (curl -F image=@pano.jpg ...)"
T = TypeVar("T")
DECODED = ("JPEG", "PNG")  # what the service takes; OpenCV decodes a few more formats, which get a 415 if it cannot


def decode_upload(data: bytes, filename: str, check: Callable[[int, int], T]) -> tuple[np.ndarray, T]:
    """(the upload as an H×W×3 uint8 RGB array, what check returned). check(width, height) runs on the header,
    before decoding (a Localizer's `check`: it raises QueryError naming the setting or the limit); bad bytes raise
    QueryError 400 / 413 / 415."""
    name = f"the upload {filename!r}"
    try:
        width, height, kind = image_size(data, name)
    except QueryError as err:
        raise QueryError(err.key, f"{err}. {SEND}" if err.status != 413 else str(err), err.status) from None
    checked = check(width, height)
    try:
        return decode_rgb(data, name, fix="Send the complete file again, or re-save it as JPEG or PNG"), checked
    except DatasetFileError as err:
        raise QueryError("image", str(err), 400 if kind in DECODED else 415) from None
