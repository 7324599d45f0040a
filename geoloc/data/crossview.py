"""Cross-view pair datasets (CVUSA, CVACT, synthetic) with the alignment switch of the paper's ablation.

alignment = "ipt"   street panorama → aerial-like image (the paper's inverse polar transform); aerial as is.
alignment = "polar" aerial → street-like polar image (SAFA); panorama resized to the same size.
alignment = "none"  no geometric alignment (the "w/o IPT" row): panorama and aerial only resized.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from geoloc.data import polar
from geoloc.data.splits import cvact_pairs, cvusa_pairs
from geoloc.data.validate import check_files, require_complete
from geoloc.engine.sampling import item_rng, split_key

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
ALIGNMENTS = ("ipt", "polar", "none")


@dataclass
class CrossViewDataConfig:
    name: str = "synthetic"  # synthetic | cvusa | cvact
    root: str | None = None
    split: str = "val"  # the split evaluate.py scores
    alignment: str = "ipt"
    aerial_size: int = 288  # the paper's 288x288 for both branches under IPT
    pano_size: list[int] = field(default_factory=lambda: [112, 616])  # H, W for polar / none
    batch_size: int = 64
    val_batch_size: int = 0  # 0 = batch_size
    rotation_deg: float = 0.0  # train: rotate the aerial-like query by U(-r, r) degrees (panorama column roll)
    color_jitter: float = 0.0  # train: brightness/contrast/saturation jitter strength, 0 = off
    joint_flip_rotate: bool = False  # train: flip / rotate by k*90° the aerial and the panorama consistently
    check_files: str = "decode"  # decode | exists | off
    max_train: int = 0  # 0 = all; for quick runs
    max_val: int = 0
    # synthetic only: what to generate on first use
    preset: str = "small"
    train_size: int = 1200
    val_size: int = 300
    seed: int = 0  # the synthetic world (which places are rendered); the run's `seed` drives augmentation
    workers: int = 2

    def __post_init__(self):
        if self.name not in ("synthetic", "cvusa", "cvact"):
            raise ValueError(f"unknown cross-view dataset {self.name!r}; choose dataset=synthetic, cvusa or cvact")
        if self.alignment not in ALIGNMENTS:
            raise ValueError(f"dataset.alignment must be one of {ALIGNMENTS}, got {self.alignment!r}")
        if self.batch_size < 1:
            raise ValueError(f"dataset.batch_size must be >= 1, got {self.batch_size}")
        if self.name != "synthetic" and not self.root:
            raise ValueError(f"dataset={self.name} needs dataset.root=/path/to/{self.name.upper()} (it is missing)")
        if self.aerial_size < 16 or len(self.pano_size) != 2 or min(self.pano_size) < 8:
            raise ValueError(f"image sizes too small: aerial_size={self.aerial_size}, pano_size={self.pano_size}")


def read_rgb(path: Path) -> np.ndarray:
    require_complete(path)  # a truncated JPEG would decode with a grey fill and only a libjpeg warning
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise OSError(f"cannot decode image {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def split_pairs(cfg: CrossViewDataConfig, split: str) -> list[tuple[Path, Path]]:
    """(street, aerial) paths of one split. The synthetic dataset is generated on first use (CVUSA layout)."""
    root = synthetic_root(cfg) if cfg.name == "synthetic" else cfg.root
    pairs = cvact_pairs(root, split) if cfg.name == "cvact" else cvusa_pairs(root, split)
    limit = cfg.max_train if split == "train" else cfg.max_val
    pairs = pairs[:limit] if limit else pairs
    check_files([p for pair in pairs for p in pair], root, split, cfg.check_files)
    return pairs


def synthetic_root(cfg: CrossViewDataConfig) -> Path:
    from geoloc.data.synthetic import ensure_dataset

    root = Path(cfg.root).expanduser() if cfg.root else default_cache() / (
        f"cvusa-{cfg.preset}-{cfg.train_size}-{cfg.val_size}-seed{cfg.seed}")
    return Path(ensure_dataset("cvusa", root, preset=cfg.preset, train=cfg.train_size, val=cfg.val_size,
                               seed=cfg.seed, workers=cfg.workers))


def default_cache() -> Path:
    import os

    return Path(os.environ.get("GEOLOC_CACHE", Path.home() / ".cache" / "geoloc")) / "synthetic"


class CrossViewPairs(Dataset):
    """Item: {"query": 3×Hq×Wq float (street, aligned), "reference": 3×Hr×Wr float (aerial),
    "index": position in the split (= place id)}. Keys may be ints or (index, epoch) pairs.

    `augment_seed` (the run's top-level `seed`) seeds the train-time augmentation per (seed, epoch, index)."""

    def __init__(self, pairs: list[tuple[Path, Path]], cfg: CrossViewDataConfig, train: bool, cvact: bool = False,
                 augment_seed: int = 0):
        self.pairs, self.cfg, self.train, self.cvact = pairs, cfg, train, cvact
        self.augment_seed = augment_seed

    def __len__(self) -> int:
        return len(self.pairs)

    def load(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        street, aerial = (read_rgb(p) for p in self.pairs[i])
        if self.cvact:  # full sphere → the horizon band, as SAFA does (rows 208:624 of 832)
            h = street.shape[0]
            street = street[h // 4 : 3 * h // 4]
        return street, aerial

    def __getitem__(self, key) -> dict:
        index, _ = split_key(key)
        street, aerial = self.load(index)
        rng = item_rng(self.augment_seed, key) if self.train else None
        query, reference = align(street, aerial, self.cfg, rng)
        return {"query": to_tensor(query, rng, self.cfg.color_jitter),
                "reference": to_tensor(reference, rng, self.cfg.color_jitter), "index": index}


def align(street: np.ndarray, aerial: np.ndarray, cfg: CrossViewDataConfig,
          rng: np.random.Generator | None) -> tuple[np.ndarray, np.ndarray]:
    """Apply the alignment switch (and the train-time augmentation) to one decoded pair."""
    if rng is not None and cfg.joint_flip_rotate:
        street, aerial = flip_rotate(street, aerial, int(rng.integers(4)), bool(rng.integers(2)))
    if rng is not None and cfg.rotation_deg > 0:
        # rotating the aerial-like image by θ is a circular shift of the panorama by θ/360 of its width
        shift = int(round(rng.uniform(-cfg.rotation_deg, cfg.rotation_deg) / 360.0 * street.shape[1]))
        street = np.roll(street, shift, axis=1)
    s = cfg.aerial_size
    pano_hw = tuple(cfg.pano_size)
    if cfg.alignment == "ipt":
        return polar.street_to_aerial(street, (s, s)), resize(aerial, (s, s))
    if cfg.alignment == "polar":
        return resize(street, pano_hw), polar.aerial_to_polar(aerial, pano_hw)
    return resize(street, pano_hw), resize(aerial, (s, s))


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


def build(cfg: CrossViewDataConfig, split: str, train: bool, augment_seed: int = 0) -> CrossViewPairs:
    """`augment_seed`: the run's `seed` (trainer.seed), so a seed sweep varies the augmentation too."""
    return CrossViewPairs(split_pairs(cfg, split), cfg, train=train, cvact=cfg.name == "cvact",
                          augment_seed=augment_seed)
