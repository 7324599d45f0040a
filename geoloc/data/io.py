"""Reading images from disk: complete files only (a truncated or cut JPEG would decode with a grey fill)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geoloc.data.validate import decode_rgb


def read_rgb(path: Path, min_size: tuple[int, int] | None = None) -> np.ndarray:
    """The image file `path` as H×W×3 uint8 RGB; a missing, incomplete or corrupt file raises, naming it.
    min_size: the (H, W) a JPEG may be decoded down to (reduced-scale DCT decoding, validate.decode_rgb)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise FileNotFoundError(f"image not found: {path}") from None
    return decode_rgb(data, path, min_size=min_size)
