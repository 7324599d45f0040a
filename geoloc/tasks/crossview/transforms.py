"""The transforms every cross-view dataset shares: decoding a view, the alignment switch of the paper's ablation,
the joint flip / rotation augmentation, and the tensor encoding.

alignment = "ipt"   street panorama → aerial-like image (the paper's inverse polar transform); aerial as is.
alignment = "polar" aerial → street-like polar image (SAFA); panorama resized to the same size.
alignment = "none"  no geometric alignment (the "w/o IPT" row): panorama and aerial only resized.

`cfg` below is the dataset config (geoloc.tasks.crossview.data_config.CrossViewDataConfig): its alignment,
sizes and augmentation keys.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from geoloc.data import polar
from geoloc.data.io import read_rgb
from geoloc.tasks.crossview.views import north_window

if TYPE_CHECKING:
    from geoloc.tasks.crossview.data_config import CrossViewDataConfig

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)


IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


def load_view(path: Path, view: str) -> np.ndarray:
    street = read_rgb(path)
    return horizon_band(street) if view == "sphere" else street


def horizon_band(sphere: np.ndarray) -> np.ndarray:
    """A full-sphere panorama's horizon band, rows H/4 to 3H/4, as SAFA cuts CVACT's (rows 208:624 of 832)."""
    h = sphere.shape[0]
    return sphere[h // 4 : 3 * h // 4]


def align(street: np.ndarray, aerial: np.ndarray, cfg: CrossViewDataConfig,
          rng: np.random.Generator | None, view: str = "panorama") -> tuple[np.ndarray, np.ndarray]:
    """Apply the alignment switch (and the train-time augmentation) to one decoded pair."""
    street, aerial = augment(street, aerial, cfg, rng)
    if cfg.fov < 360.0:  # the camera's window on the north-aligned panorama; at fov 360 no random number is drawn
        heading = float(rng.uniform(0.0, 360.0)) if rng is not None and cfg.random_heading else 0.0
        street = north_window(street, cfg.fov, heading)
    return align_query(street, cfg, view), align_reference(aerial, cfg)


def augment(street: np.ndarray, aerial: np.ndarray, cfg: CrossViewDataConfig,
            rng: np.random.Generator | None) -> tuple[np.ndarray, np.ndarray]:
    """The train-time geometric augmentation of one decoded pair (none when rng is None): the joint flip /
    quarter-turn, then the rotation of the query alone."""
    if rng is not None and cfg.joint_flip_rotate:
        street, aerial = flip_rotate(street, aerial, int(rng.integers(4)), bool(rng.integers(2)))
    if rng is not None and cfg.rotation_deg > 0:
        # rotating the aerial-like image by θ is a circular shift of the panorama by θ/360 of its width
        shift = int(round(rng.uniform(-cfg.rotation_deg, cfg.rotation_deg) / 360.0 * street.shape[1]))
        street = np.roll(street, shift, axis=1)
    return street, aerial


def align_query(street: np.ndarray, cfg: CrossViewDataConfig, view: str = "panorama",
                wrapped: bool = False) -> np.ndarray:
    """wrapped: the panorama ends with a copy of its first column (a window of views.view_canvases)."""
    s = cfg.aerial_size
    if view == "image":  # a photo: no polar geometry, the square input of the aerial branch's size
        return resize(street, (s, s))
    if cfg.alignment == "ipt":
        return polar.street_to_aerial(street, (s, s), wrapped=wrapped)
    return resize(street[:, :-1] if wrapped else street, tuple(cfg.pano_size))


def align_reference(aerial: np.ndarray, cfg: CrossViewDataConfig) -> np.ndarray:
    if cfg.alignment == "polar":
        return polar.aerial_to_polar(aerial, tuple(cfg.pano_size))
    return resize(aerial, (cfg.aerial_size, cfg.aerial_size))


def flip_rotate(street: np.ndarray, aerial: np.ndarray, quarter_turns: int, flip: bool):
    """The same place seen in a mirrored and/or rotated world: a new, geometrically true pair.

    Panorama column j looks along bearing 180° + 360°·j/W (north at the centre). Mirroring the aerial east-west
    maps bearing b to -b, i.e. column j to column -j (mod W); turning the aerial clockwise by 90° makes column j
    show what column j - W/4 showed.
    """
    w = street.shape[1]
    if flip:
        aerial = aerial[:, ::-1]
        street = street[:, (-np.arange(w)) % w]
    for _ in range(quarter_turns):
        aerial = cv2.rotate(np.ascontiguousarray(aerial), cv2.ROTATE_90_CLOCKWISE)
        street = np.roll(street, w // 4, axis=1)
    return np.ascontiguousarray(street), np.ascontiguousarray(aerial)


def resize(img: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    if img.shape[:2] == tuple(hw):
        return img
    return cv2.resize(img, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)


def to_tensor(img: np.ndarray, rng: np.random.Generator | None = None, jitter: float = 0.0) -> torch.Tensor:
    """HxWx3 uint8 → 3xHxW float, ImageNet-normalised, with optional photometric jitter."""
    x = img.astype(np.float32) / 255.0
    if rng is not None and jitter > 0:
        b, c, s = rng.uniform(1 - jitter, 1 + jitter, size=3)
        x = x * b
        mean = x.mean()
        x = (x - mean) * c + mean
        gray = x.mean(axis=2, keepdims=True)
        x = np.clip((x - gray) * s + gray, 0.0, 1.0)
    x = (x - IMAGENET_MEAN) / IMAGENET_STD
    return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1), dtype=np.float32))
