"""An uploaded file -> an H×W×3 uint8 RGB image, or an UploadError saying what is wrong and what to do.

The pixel count is read from the header (PIL opens lazily: `Image.open(...).size` parses the header only) before
anything is decoded, so a decompression bomb (a few kB of PNG that inflates to gigabytes) is refused unread.
Completeness is checked on the bytes (geoloc.data.validate: libjpeg would fill a truncated JPEG with grey and
only print a warning), then OpenCV decodes, as the dataset readers do (geoloc.data.io.read_rgb).
"""

from __future__ import annotations

import io

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from geoloc.data.validate import content_problem

# what to tell a client that sent something unusable
SEND = "send the street image as the multipart/form-data file field 'image' (curl -F image=@pano.jpg ...)"


class UploadError(ValueError):
    """A bad upload: `status` is the HTTP status to answer (400, 413, 415), the message says what to do."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


def image_header(data: bytes, filename: str) -> tuple[int, int, str]:
    """(width, height, PIL's format name) from the file's header, without decoding the pixels."""
    if not data:
        raise UploadError(400, f"the upload {filename!r} is empty (0 bytes): {SEND}")
    try:
        with Image.open(io.BytesIO(data)) as header:
            return (*header.size, header.format)
    except Image.DecompressionBombError as err:  # PIL's own guard, far above max_pixels
        raise UploadError(413, f"the upload {filename!r} is too large: {err}. Downscale it and send it again")
    except (UnidentifiedImageError, SyntaxError, ValueError, OSError):  # what PIL raises on a header it cannot read
        raise UploadError(415, f"the upload {filename!r} is not an image (it starts with {data[:16]!r}): "
                               f"{SEND}, as JPEG or PNG") from None


def decode_upload(data: bytes, filename: str, max_pixels: int) -> np.ndarray:
    """The upload as an H×W×3 uint8 RGB array; raises UploadError (400 / 413 / 415) on bad input."""
    width, height, kind = image_header(data, filename)
    if width * height > max_pixels:
        raise UploadError(413, f"the image {filename!r} is {width}x{height} = {width * height:,} pixels, over this "
                               f"server's limit of {max_pixels:,} (max_pixels): downscale it "
                               "(the network sees a few hundred pixels across anyway) and send it again")
    problem = content_problem(data)
    if problem:
        raise UploadError(400, f"the upload {filename!r} is damaged: {problem}. Send the complete file")
    try:
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    except cv2.error:
        bgr = None
    if bgr is None or bgr.size == 0:
        if kind in ("JPEG", "PNG"):
            raise UploadError(400, f"the upload {filename!r} is a corrupt {kind}: its header reads {width}x{height} "
                                   "but the image data does not decode. Send the file again, or re-save it")
        raise UploadError(415, f"the upload {filename!r} is a {kind} image, which OpenCV does not decode: {SEND}, "
                               "as JPEG or PNG")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
