"""The cross-view data module: any registered dataset's RetrievalSplit → training pairs and evaluation sets, with
the transforms every dataset shares and the alignment switch of the paper's ablation.

alignment = "ipt"   street panorama → aerial-like image (the paper's inverse polar transform); aerial as is.
alignment = "polar" aerial → street-like polar image (SAFA); panorama resized to the same size.
alignment = "none"  no geometric alignment (the "w/o IPT" row): panorama and aerial only resized.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import cv2
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import Dataset

from geoloc import registry
from geoloc.config import ConfigError, checked
from geoloc.data import polar
from geoloc.data.heading import check_fov, crop_view, eval_heading, north_window, query_candidates
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.data.validate import check_files, require_complete
from geoloc.engine.sampling import item_rng, split_key

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
ALIGNMENTS = ("ipt", "polar", "none")
NEIGHBOURS = 128  # GPS neighbours listed per training pair (Sample4Geo's neighbour_range)


@dataclass
class CrossViewDataConfig:
    """The keys every cross-view dataset shares (transforms, batches, checks). The dataset's own keys (e.g.
    VIGOR's `setting`, the synthetic world's `preset`) go to its reader, registered under `name`
    (geoloc/data/readers.py), which checks them against its signature."""

    name: str = "synthetic"  # a registered reader: synthetic | cvusa | cvact | vigor | u1652 | a plug-in's
    module: str | None = None  # a plug-in reader's module (docs/extending.md)
    root: str | None = None  # null = the embedded synthetic data, for the readers that have it
    split: str = "val"  # the split evaluate.py scores
    val_split: str = "val"  # the split validated after each training epoch
    alignment: str = "ipt"
    aerial_size: int = 288  # the paper's 288x288 for both branches under IPT
    pano_size: list[int] = field(default_factory=lambda: [112, 616])  # H, W for polar / none
    batch_size: int = 64
    val_batch_size: int = 0  # 0 = batch_size
    rotation_deg: float = 0.0  # train: rotate the aerial-like query by U(-r, r) degrees (panorama column roll)
    color_jitter: float = 0.0  # train: brightness/contrast/saturation jitter strength, 0 = off
    joint_flip_rotate: bool = False  # train: flip / rotate by k*90° the aerial and the panorama consistently
    fov: float = 360.0  # the street camera's field of view in degrees, (0, 360]; the rest of the canvas is 0
    random_heading: bool = False  # train: the view at a random bearing; eval: unknown heading, searched
    heading_steps: int = 36  # eval with random_heading: candidate headings 360·k/K per query (docs/heading.md)
    check_files: str = "decode"  # decode | exists | off
    max_train: int = 0  # 0 = all; for quick runs (one-to-one splits keep their pairs; others cut the queries)
    max_val: int = 0

    def __post_init__(self):
        if self.alignment not in ALIGNMENTS:
            raise ValueError(f"dataset.alignment must be one of {ALIGNMENTS}, got {self.alignment!r}")
        if self.batch_size < 1:
            raise ValueError(f"dataset.batch_size must be >= 1, got {self.batch_size}")
        if self.aerial_size < 16 or len(self.pano_size) != 2 or min(self.pano_size) < 8:
            raise ValueError(f"image sizes too small: aerial_size={self.aerial_size}, pano_size={self.pano_size}")
        check_fov(self.fov, "dataset.fov")
        if self.heading_steps < 1:
            raise ValueError(f"dataset.heading_steps must be >= 1 (candidate headings per query), got "
                             f"{self.heading_steps}")

    @property
    def limited_view(self) -> bool:
        """Whether query views differ from the north-aligned full panorama (a narrower fov or a random heading)."""
        return self.fov < 360.0 or self.random_heading


SHARED_KEYS = tuple(f.name for f in fields(CrossViewDataConfig))


def as_dict(section) -> dict:
    """A dataset section as a plain dict: a DictConfig, a dict, or a CrossViewDataConfig (shared keys only)."""
    if isinstance(section, CrossViewDataConfig):
        return asdict(section)
    return OmegaConf.to_container(section, resolve=True) if isinstance(section, DictConfig) else dict(section)


def shared_config(section) -> CrossViewDataConfig:
    """The shared keys of a dataset section, checked; the reader's own keys are checked by read_split."""
    params = as_dict(section)
    return checked({k: v for k, v in params.items() if k in SHARED_KEYS}, CrossViewDataConfig, "dataset")


def check_reader_keys(section) -> None:
    """The reader's own keys against its signature, without reading anything (start-up checks)."""
    registry.check("dataset", as_dict(section), exclude=SHARED_KEYS, runtime=("root", "split"))


def read_split(section, split: str) -> RetrievalSplit:
    """The RetrievalSplit `split` of the dataset the section names, with the section's limits and file checks."""
    cfg = shared_config(section)
    out = registry.build("dataset", as_dict(section), exclude=SHARED_KEYS, root=cfg.root, split=split)
    if not isinstance(out, RetrievalSplit):
        raise TypeError(f"dataset {cfg.name!r}: its reader returned {type(out).__name__}, not a RetrievalSplit "
                        "(docs/extending.md)")
    if out.query_view in ("image", "aerial") and (cfg.alignment != "none" or cfg.joint_flip_rotate
                                                   or cfg.rotation_deg > 0 or cfg.limited_view):
        raise ConfigError(f"dataset {cfg.name!r} has photo queries (e.g. drone views): polar alignment, the joint "
                          "flip/rotate and rotation of panoramas and the panorama field of view / heading do not "
                          "apply; set dataset.alignment=none dataset.joint_flip_rotate=false dataset.rotation_deg=0 "
                          "dataset.fov=360 dataset.random_heading=false")
    limit = cfg.max_train if split == "train" else cfg.max_val
    if limit and limit < out.num_queries:
        out = limited(out, limit)
    check_files(paths_to_check(out), out.root, split, cfg.check_files)
    return out


def limited(split: RetrievalSplit, n: int) -> RetrievalSplit:
    """The first n queries; a one-to-one split keeps its pairs (the first n references too)."""
    take = lambda a: None if a is None else a[:n]  # noqa: E731
    if split.one_to_one:
        return replace(split, queries=split.queries[:n], references=split.references[:n],
                       positives=split.positives[:n], query_latlon=take(split.query_latlon),
                       reference_latlon=take(split.reference_latlon), query_xy=take(split.query_xy),
                       reference_xy=take(split.reference_xy))
    return replace(split, queries=split.queries[:n], positives=split.positives[:n],
                   semi_positives=take(split.semi_positives), query_latlon=take(split.query_latlon),
                   query_xy=take(split.query_xy), query_labels=take(split.query_labels))


def paths_to_check(split: RetrievalSplit) -> list[Path]:
    if split.one_to_one:  # pair by pair, as the one-to-one readers list them
        return [p for pair in zip(split.queries, split.references) for p in pair]
    return [*split.queries, *split.references]


def read_rgb(path: Path) -> np.ndarray:
    require_complete(path)  # a truncated JPEG would decode with a grey fill and only a libjpeg warning
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise OSError(f"cannot decode image {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


class CrossViewPairs(Dataset):
    """Training (and one-to-one validation) pairs: item i is query i with its positive reference.

    Item: {"query": 3×Hq×Wq float (street, aligned), "reference": 3×Hr×Wr float (aerial), "index": i (position in
    the split), "label": the positive reference's index (the place: queries of one place share it)}. Keys may be
    ints or (index, epoch) pairs. `augment_seed` (the run's top-level `seed`) seeds the train-time augmentation
    per (seed, epoch, index).

    `heading_search` (evaluation with dataset.random_heading): query i is seen at heading eval_heading(i) with
    dataset.fov, and item["query"] is its K×3×H×W candidate inputs (heading 360·k/K each, geoloc/data/heading.py),
    item["heading"] the true heading in degrees."""

    def __init__(self, split: RetrievalSplit, cfg: CrossViewDataConfig, train: bool, augment_seed: int = 0,
                 heading_search: bool = False):
        if split.aerial_queries:
            raise ValueError(f"{split.name}: pairs need ground-side queries; this split's queries are aerial images")
        self.split, self.cfg, self.train = split, cfg, train
        self.heading_search = heading_search
        self.augment_seed = augment_seed
        self.labels = split.labels()
        self._neighbours = None

    def __len__(self) -> int:
        return self.split.num_queries

    @property
    def neighbours(self) -> np.ndarray | None:
        """(N, k) the other pairs nearest by GPS, nearest first, for the GPS samplers; None without positions."""
        if self.split.query_latlon is None:
            return None
        if self._neighbours is None:
            from geoloc.data.neighbours import gps_neighbour_lists

            k = min(NEIGHBOURS, len(self) - 1)
            self._neighbours = gps_neighbour_lists(self.split.query_latlon, k, self.labels)
        return self._neighbours

    def __getitem__(self, key) -> dict:
        index, _ = split_key(key)
        label = int(self.labels[index])
        street = load_view(self.split.queries[index], self.split.query_view)
        aerial = read_rgb(self.split.references[label])
        if self.heading_search:
            heading = eval_heading(index)
            view = crop_view(street, self.cfg.fov, heading)
            candidates, _ = query_candidates(view, self.cfg, self.split.query_view, self.cfg.fov,
                                             self.cfg.heading_steps)
            return {"query": candidates, "reference": to_tensor(align_reference(aerial, self.cfg)), "index": index,
                    "label": label, "heading": heading}
        rng = item_rng(self.augment_seed, key) if self.train else None
        query, reference = align(street, aerial, self.cfg, rng, self.split.query_view)
        return {"query": to_tensor(query, rng, self.cfg.color_jitter),
                "reference": to_tensor(reference, rng, self.cfg.color_jitter), "index": index, "label": label}


class ViewImages(Dataset):
    """One side of an evaluation split, for galleries that are not one-to-one: item {"image": 3×H×W float,
    "index": i}. `view` is "aerial" for aerial images (the reference branch's input) or the query view of the
    split's ground-side images ("panorama", "sphere", "image")."""

    def __init__(self, paths: list[Path], view: str, cfg: CrossViewDataConfig):
        self.paths, self.view, self.cfg = list(paths), view, cfg

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, key) -> dict:
        index, _ = split_key(key)
        if self.view == "aerial":
            image = align_reference(read_rgb(self.paths[index]), self.cfg)
        else:
            street = load_view(self.paths[index], self.view)
            if self.view != "image":
                street = north_window(street, self.cfg.fov, 0.0)
            image = align_query(street, self.cfg, self.view)
        return {"image": to_tensor(image), "index": index}


def load_view(path: Path, view: str) -> np.ndarray:
    street = read_rgb(path)
    if view == "sphere":  # full sphere → the horizon band, as SAFA does for CVACT (rows 208:624 of 832)
        h = street.shape[0]
        street = street[h // 4 : 3 * h // 4]
    return street


def align(street: np.ndarray, aerial: np.ndarray, cfg: CrossViewDataConfig,
          rng: np.random.Generator | None, view: str = "panorama") -> tuple[np.ndarray, np.ndarray]:
    """Apply the alignment switch (and the train-time augmentation) to one decoded pair."""
    if rng is not None and cfg.joint_flip_rotate:
        street, aerial = flip_rotate(street, aerial, int(rng.integers(4)), bool(rng.integers(2)))
    if rng is not None and cfg.rotation_deg > 0:
        # rotating the aerial-like image by θ is a circular shift of the panorama by θ/360 of its width
        shift = int(round(rng.uniform(-cfg.rotation_deg, cfg.rotation_deg) / 360.0 * street.shape[1]))
        street = np.roll(street, shift, axis=1)
    if cfg.fov < 360.0:  # the camera's window on the north-aligned panorama; fov 360 draws nothing (as before)
        heading = float(rng.uniform(0.0, 360.0)) if rng is not None and cfg.random_heading else 0.0
        street = north_window(street, cfg.fov, heading)
    return align_query(street, cfg, view), align_reference(aerial, cfg)


def align_query(street: np.ndarray, cfg: CrossViewDataConfig, view: str = "panorama") -> np.ndarray:
    s = cfg.aerial_size
    if view == "image":  # a photo: no polar geometry, the square input of the aerial branch's size
        return resize(street, (s, s))
    if cfg.alignment == "ipt":
        return polar.street_to_aerial(street, (s, s))
    return resize(street, tuple(cfg.pano_size))


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


@dataclass
class EvalData:
    """What validation reads: the split, and either its pairs (one-to-one: both views in one loader, as the
    paper's protocol encodes them) or its two sides (queries and gallery apart: VIGOR, University-1652)."""

    split: RetrievalSplit
    pairs: CrossViewPairs | None = None
    queries: ViewImages | None = None
    references: ViewImages | None = None

    def __len__(self) -> int:
        return self.split.num_queries


def known_heading(data: EvalData) -> EvalData:
    """`data` with its pairs seen at the known heading (north), one query image each: what the figures show."""
    if data.pairs is None or not data.pairs.heading_search:
        return data
    return replace(data, pairs=CrossViewPairs(data.split, data.pairs.cfg, train=False))


def build(section, split: str, train: bool, augment_seed: int = 0) -> CrossViewPairs:
    """Training pairs of `split`. `augment_seed`: the run's `seed`, so a seed sweep varies the augmentation too."""
    return CrossViewPairs(read_split(section, split), shared_config(section), train=train, augment_seed=augment_seed)


def build_eval(section, split: str) -> EvalData:
    cfg = shared_config(section)
    data = read_split(section, split)
    if data.one_to_one:
        return EvalData(data, pairs=CrossViewPairs(data, cfg, train=False, heading_search=cfg.random_heading))
    if cfg.random_heading:
        raise ConfigError(f"dataset {cfg.name!r}: evaluation with an unknown heading (dataset.random_heading=true) "
                          "scores one-to-one splits (CVUSA, CVACT, synthetic) only; evaluate this split with "
                          "dataset.random_heading=false (a known heading, north at the centre)")
    reference_view = "image" if data.aerial_queries else "aerial"
    return EvalData(data, queries=ViewImages(data.queries, data.query_view, cfg),
                    references=ViewImages(data.references, reference_view, cfg))
