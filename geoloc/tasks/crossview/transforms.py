"""The transforms every cross-view dataset shares: decoding a view, the alignment switch of the paper's ablation,
the joint flip / rotation augmentation, and the tensor encoding.

The tensor encoding is split in two so that data workers stay at the decode limit: a worker returns each image as
3×H×W uint8 (`image_tensor`) with its colour jitter's random draws (`jitter_draw`), and the task normalises whole
batches on the training device (`normalise`, called by CrossViewTask.on_after_batch_transfer). Both halves together
give, bit for bit, the float32 ImageNet normalisation of numpy's `(x / 255 - mean) / std` (and the jitter's float64
arithmetic), so augmentation stays keyed on (seed, epoch, index).

alignment = "ipt"   street panorama → aerial-like image (the paper's inverse polar transform); aerial as is.
alignment = "ground" full-sphere panorama → the ground plane seen from dataset.camera_height_m, dataset.ground_extent_m
                    metres across (geoloc.data.polar.street_to_ground); aerial as is.
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

# uint8 value v -> v / 255 in float32, as numpy divides a float32 image by 255.0
_UNIT = np.arange(256, dtype=np.float32) / 255.0


def load_view(path: Path, view: str, min_size: tuple[int, int] | None = None) -> np.ndarray:
    """min_size: decode a JPEG at a reduced scale no smaller than this H×W (`decode_size`); None: full size."""
    street = read_rgb(path, min_size)
    return horizon_band(street) if view == "sphere" else street


def decode_size(cfg: CrossViewDataConfig, view: str) -> tuple[int, int] | None:
    """The H×W an image of `view` may be decoded down to (JPEG DCT scaling, geoloc.data.validate.decode_rgb): the
    size the transforms resize it to, where a resize is all that changes its geometry (aerial tiles outside polar
    alignment, photos). None: full size (panoramas go through the polar transforms, the column roll and the field of
    view at their own resolution; dataset.reduced_decode=false)."""
    if cfg.reduced_decode and (view == "image" or (view == "aerial" and cfg.alignment != "polar")):
        return cfg.aerial_size, cfg.aerial_size
    return None


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
    quarter-turn, then the rotation of the query alone, then (photo queries) the rotation of the tile alone."""
    if rng is not None and cfg.joint_flip_rotate:
        street, aerial = flip_rotate(street, aerial, int(rng.integers(4)), bool(rng.integers(2)))
    if rng is not None and cfg.rotation_deg > 0:
        # rotating the aerial-like image by θ is a circular shift of the panorama by θ/360 of its width
        shift = int(round(rng.uniform(-cfg.rotation_deg, cfg.rotation_deg) / 360.0 * street.shape[1]))
        street = np.roll(street, shift, axis=1)
    if rng is not None and cfg.aerial_rotation_deg > 0:  # photo queries only (datasets.read_split checks)
        aerial = rotate_about_centre(aerial, float(rng.uniform(-cfg.aerial_rotation_deg, cfg.aerial_rotation_deg)))
    return street, aerial


def rotate_about_centre(img: np.ndarray, angle_deg: float) -> np.ndarray:
    """`img` turned counter-clockwise by angle_deg about its centre, the same size, black outside (the corners)."""
    h, w = img.shape[:2]
    matrix = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), angle_deg, 1.0)
    return cv2.warpAffine(img, matrix, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def align_query(street: np.ndarray, cfg: CrossViewDataConfig, view: str = "panorama",
                wrapped: bool = False) -> np.ndarray:
    """wrapped: the panorama ends with a copy of its first column (a window of views.view_canvases)."""
    s = cfg.aerial_size
    if view == "image":  # a photo: no polar geometry, the square input of the aerial branch's size
        return resize(street, (s, s), cfg.resize_interpolation)
    if cfg.alignment == "ipt":
        return polar.street_to_aerial(street, (s, s), wrapped=wrapped)
    if cfg.alignment == "ground":  # a sphere's horizon band (datasets.read_split checks)
        return polar.street_to_ground(street, (s, s), cfg.ground_extent_m, cfg.camera_height_m, wrapped)
    return resize(street[:, :-1] if wrapped else street, tuple(cfg.pano_size), cfg.resize_interpolation)


def align_reference(aerial: np.ndarray, cfg: CrossViewDataConfig) -> np.ndarray:
    if cfg.alignment == "polar":
        return polar.aerial_to_polar(aerial, tuple(cfg.pano_size))
    return resize(aerial, (cfg.aerial_size, cfg.aerial_size), cfg.resize_interpolation)


def flip_rotate(street: np.ndarray, aerial: np.ndarray, quarter_turns: int, flip: bool):
    """The same place seen in a mirrored and/or rotated world: a new, geometrically true pair.

    Panorama column j looks along bearing 180° + 360°·j/W (north at the centre). Mirroring the aerial east-west
    maps bearing b to -b, i.e. column j to column -j (mod W); turning the aerial clockwise by 90° makes column j
    show what column j - W/4 showed.
    """
    shift = (quarter_turns % 4) * (street.shape[1] // 4)
    if flip:  # column j <- column -j (mod W): the mirrored columns (cv2.flip) rolled by one
        street, shift = cv2.flip(street, 1), shift + 1
    if shift:  # k turns at once: one roll of the panorama by k·(W // 4) (with the flip's)
        street = np.roll(street, shift, axis=1)
    return np.ascontiguousarray(street), turned_tile(aerial, quarter_turns, flip)


def turned_tile(aerial: np.ndarray, quarter_turns: int, flip: bool) -> np.ndarray:
    """flip_rotate's aerial side alone (H×W×C, any C): mirrored east-west, then turned clockwise by quarter turns."""
    if flip:
        aerial = cv2.flip(aerial, 1)
    if quarter_turns % 4:
        aerial = cv2.rotate(np.ascontiguousarray(aerial), _CLOCKWISE_TURNS[quarter_turns % 4])
    return np.ascontiguousarray(aerial)


_CLOCKWISE_TURNS = {1: cv2.ROTATE_90_CLOCKWISE, 2: cv2.ROTATE_180, 3: cv2.ROTATE_90_COUNTERCLOCKWISE}


_INTERPOLATION = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR}


def resize(img: np.ndarray, hw: tuple[int, int], interpolation: str = "area") -> np.ndarray:
    """interpolation: dataset.resize_interpolation. "linear" is bilinear only where each side shrinks by less than
    2x (what a reduced JPEG decode leaves) or grows; a larger reduction is an area average, where bilinear would
    alias."""
    if img.shape[:2] == tuple(hw):
        return img
    if interpolation == "linear" and (img.shape[0] >= 2 * hw[0] or img.shape[1] >= 2 * hw[1]):
        interpolation = "area"
    return cv2.resize(img, (hw[1], hw[0]), interpolation=_INTERPOLATION[interpolation])


def to_tensor(img: np.ndarray) -> torch.Tensor:
    """H×W×3 uint8 → 3×H×W float32, ImageNet-normalised (what the apps feed a branch)."""
    return normalise(image_tensor(img))


def image_tensor(img: np.ndarray) -> torch.Tensor:
    """H×W×3 uint8 → 3×H×W uint8 (a view of `img` where it is contiguous): what a data worker returns."""
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)


def jitter_draw(img: np.ndarray, rng: np.random.Generator, jitter: float) -> np.ndarray:
    """The photometric jitter of one H×W×3 uint8 image, drawn in the data worker: float64 [brightness b, contrast
    c, saturation s, m], each factor U(1 - jitter, 1 + jitter), and m the mean of the brightened image b·x (x =
    img / 255 in float32), summed by numpy in memory order as `normalise` needs it to the last bit."""
    b, c, s = rng.uniform(1 - jitter, 1 + jitter, size=3)
    m = (_UNIT.astype(np.float64) * b)[img].mean()  # x·b takes 256 values: a table lookup, not a float image
    return np.array([b, c, s, m])


def normalise(images: torch.Tensor, jitter: torch.Tensor | None = None) -> torch.Tensor:
    """(..., 3, H, W) uint8 → float32 ImageNet-normalised, (x / 255 - mean) / std per channel, on images' device.

    jitter: (..., 4) float64 rows of `jitter_draw`, one per image, or None. With it each image x in [0, 1] becomes
    y = (b·x - m)·c + m, then z = clip((y - g)·s + g, 0, 1) with g its per-pixel channel mean, in float64, then
    normalised and rounded to float32. Each step is one elementwise IEEE op in numpy's order (no fused
    multiply-add; divisions by device tensors, which CUDA divides exactly where it would multiply by the
    reciprocal of a Python scalar), so the result equals the per-image numpy computation bit for bit (tests check
    it on the CPU)."""
    if images.dtype != torch.uint8 or images.shape[-3] != 3:
        raise ValueError(f"normalise takes (..., 3, H, W) uint8 images, got {images.dtype} {tuple(images.shape)}")
    device = images.device
    x = images.float() / torch.tensor(255.0, device=device)
    if jitter is None:
        mean, std = (torch.from_numpy(v).to(device).view(3, 1, 1) for v in (IMAGENET_MEAN, IMAGENET_STD))
        return (x - mean) / std
    b, c, s, m = jitter.to(device, torch.float64).reshape(-1, 4).view(-1, 4, 1, 1, 1).unbind(1)  # each (N,1,1,1)
    y = x.double().reshape(-1, *images.shape[-3:]).mul_(b).sub_(m).mul_(c).add_(m)  # in place: one float64 image
    gray = (y[:, 0:1] + y[:, 1:2]).add_(y[:, 2:3]).div_(torch.tensor(3.0, dtype=torch.float64, device=device))
    z = y.sub_(gray).mul_(s).add_(gray).clamp_(0.0, 1.0)
    mean, std = (torch.from_numpy(v).to(device, torch.float64).view(3, 1, 1) for v in (IMAGENET_MEAN, IMAGENET_STD))
    return z.sub_(mean).div_(std).float().reshape(images.shape)


def normalised(batch: dict, keys=("query", "reference", "image", "query_views")) -> dict:
    """`batch` with its uint8 images under `keys` normalised (`normalise`, with their `<key>_jitter` draws, which
    it drops); float images (already normalised) are left as they are."""
    out = dict(batch)
    for key in keys:
        jitter = out.pop(f"{key}_jitter", None)
        if isinstance(out.get(key), torch.Tensor) and out[key].dtype == torch.uint8:
            out[key] = normalise(out[key], jitter)
    return out
