"""Decoded images kept in memory, for training sets small enough to hold.

Decoding is most of a loader's work on the small CPU recipes (VIGOR's 256x512 panorama JPEGs and 256x256 PNG tiles:
1.9 of 2.6 ms per pair, benchmarks/README.md), and the same files are decoded again every epoch. With
dataset.cache_decoded=true each image is decoded once per process (the main one with trainer.num_workers=0, else each
loader worker) and reused: the items are the same arrays, so the augmentation that follows, and the figures, do not
change. Kept images are read-only, so an in-place edit downstream fails loudly instead of altering later epochs."""

from __future__ import annotations

from typing import Callable, Hashable

import numpy as np


class DecodedImages:
    """`get(key, decode)`: decode() the first time `key` is asked for, the kept array after; with enabled=False,
    decode() every time (nothing kept)."""

    def __init__(self, enabled: bool):
        self._kept: dict[Hashable, np.ndarray] | None = {} if enabled else None

    def get(self, key: Hashable, decode: Callable[[], np.ndarray]) -> np.ndarray:
        if self._kept is None:
            return decode()
        image = self._kept.get(key)
        if image is None:
            image = decode()
            image.setflags(write=False)
            self._kept[key] = image
        return image

    @property
    def nbytes(self) -> int:
        """Bytes held (0 when disabled)."""
        return sum(image.nbytes for image in (self._kept or {}).values())
