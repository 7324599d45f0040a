"""Spatial pyramid coding of a segmentation map (MMDIP eq. 4, after Lazebnik et al. 2006).

Level l in 0..L splits the H x W map into 2^l x 2^l cells with integer bounds (rows a*H//n to (a+1)*H//n) and
counts the pixels of each class in each cell. Level weights: 2^-L for l = 0, 2^(l-L-1) for l >= 1. The code is
the concatenation of the weighted counts, levels coarse to fine, cells row-major, classes inside each cell.

Vectorised: one bincount at the finest level. The bounds nest (floor(2a*H/2n) = floor(a*H/n)), so every coarser
level is an exact 2x2 block sum of the next finer one.
"""

from __future__ import annotations

import numpy as np


def level_weights(levels: int) -> np.ndarray:
    """The eq. 4 weight of each level 0..L."""
    l = np.arange(levels + 1, dtype=np.float64)
    w = 2.0 ** (l - levels - 1)
    w[0] = 2.0 ** -levels
    return w


def spm_dim(num_classes: int, levels: int) -> int:
    """Length of the code: C * sum_l 4^l."""
    return num_classes * sum(4**l for l in range(levels + 1))


def _cell_of(length: int, n: int) -> np.ndarray:
    """Cell index of each of `length` rows (or columns) for n cells with bounds a*length//n."""
    bounds = np.arange(n + 1) * length // n
    return np.repeat(np.arange(n), np.diff(bounds))


def spm_encode(seg: np.ndarray, num_classes: int, levels: int = 2) -> np.ndarray:
    """Eq. 4 SPM code of an H x W integer map with values in [0, num_classes).

    Returns a 1-D float32 array of length `spm_dim(num_classes, levels)`. Counts and weights are exact in float32
    (integers below 2^24 times powers of two).
    """
    seg = np.asarray(seg)
    if seg.ndim != 2:
        raise ValueError(f"spm_encode expects an H x W map, got shape {seg.shape}")
    if not np.issubdtype(seg.dtype, np.integer):
        raise ValueError(f"spm_encode expects an integer map, got dtype {seg.dtype}")
    if levels < 0:
        raise ValueError(f"levels must be >= 0, got {levels}")
    if seg.size and (seg.min() < 0 or seg.max() >= num_classes):
        raise ValueError(f"spm_encode: labels must lie in [0, {num_classes}), got [{seg.min()}, {seg.max()}]")
    h, w = seg.shape
    n = 2**levels
    row_off = _cell_of(h, n) * (n * num_classes)
    col_off = _cell_of(w, n) * num_classes
    flat = (row_off[:, None] + col_off[None, :] + seg).ravel()
    counts = np.bincount(flat, minlength=n * n * num_classes).reshape(n, n, num_classes)

    weights = level_weights(levels)
    parts = [None] * (levels + 1)
    for lvl in range(levels, -1, -1):  # fine to coarse: a loop over levels, never over cells
        parts[lvl] = (counts * weights[lvl]).astype(np.float32).ravel()
        if lvl:
            m = counts.shape[0] // 2
            counts = counts.reshape(m, 2, m, 2, num_classes).sum(axis=(1, 3))
    return np.concatenate(parts)
