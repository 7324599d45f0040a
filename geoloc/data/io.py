"""Reading images from disk: complete files only (a truncated JPEG would decode with a grey fill)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from geoloc.data.validate import require_complete


def read_rgb(path: Path) -> np.ndarray:
    require_complete(path)  # a truncated JPEG would decode with a grey fill and only a libjpeg warning
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise OSError(f"cannot decode image {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
