"""The cross-view dataset section: the keys every dataset shares (CrossViewDataConfig), checked once; the reader's
own keys (VIGOR's `setting`, the synthetic world's `preset`...) are checked against the reader's signature."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

from omegaconf import DictConfig, OmegaConf

import geoloc.datasets  # noqa: F401  (declares the dataset kind and registers the built-in readers)
from geoloc import registry
from geoloc.config import checked
from geoloc.tasks.crossview.views import check_fov

ALIGNMENTS = ("ipt", "ground", "polar", "none")
INTERPOLATIONS = ("area", "linear")


@dataclass
class CrossViewDataConfig:
    """The keys every cross-view dataset shares (transforms, batches, checks). The dataset's own keys (e.g.
    VIGOR's `setting`, the synthetic world's `preset`) go to its reader, registered under `name`
    (geoloc/datasets/), which checks them against its signature."""

    name: str = "synthetic"  # a registered reader: synthetic | cvusa | cvact | vigor | u1652 | folder | a plug-in's
    module: str | None = None  # a plug-in reader's module (docs/extending.md)
    root: str | None = None  # null = the embedded synthetic data, for the readers that have it
    split: str = "val"  # the split evaluate.py scores
    val_split: str = "val"  # the split validated after each training epoch
    alignment: str = "ipt"
    aerial_size: int = 288  # the paper's 288x288 for both branches under IPT
    pano_size: list[int] = field(default_factory=lambda: [112, 616])  # H, W for polar / none
    # alignment=ground (geoloc.data.polar.street_to_ground, full-sphere queries): the metres the aerial-like query spans
    # (the tile's extent: VIGOR's 640 px at 0.114 m, 72.96 m) and the street camera's height above the ground
    ground_extent_m: float = 72.96
    camera_height_m: float = 2.5
    batch_size: int = 64
    val_batch_size: int = 0  # 0 = batch_size
    rotation_deg: float = 0.0  # train: rotate the aerial-like query by U(-r, r) degrees (panorama column roll)
    color_jitter: float = 0.1  # train: brightness/contrast/saturation jitter strength, 0 = off
    joint_flip_rotate: bool = False  # train: flip / rotate by k*90° the aerial and the panorama consistently
    # train, photo queries only (University-1652's drone views): rotate the aerial tile alone by U(-r, r) degrees, as
    # the University-1652 baseline's satellite transform does (RandomAffine(90)); the query's bearing is unknown
    aerial_rotation_deg: float = 0.0
    fov: float = 360.0  # the street camera's field of view in degrees, (0, 360]; the rest of the canvas is 0
    random_heading: bool = False  # train: the view at a random bearing; eval: unknown heading, searched
    heading_steps: int = 36  # eval with random_heading: candidate headings 360·k/K per query (docs/heading.md)
    check_files: str = "decode"  # decode | exists | off
    # decode JPEG aerials / photos at 1/2-1/8 scale when they are resized to no less (transforms.decode_size); off
    # by default, so checkpoints from before it and the embedded default decode as they were trained; the real
    # datasets' yaml files turn it on
    reduced_decode: bool = False
    # how an aerial tile or a photo is resized to aerial_size (and the `none` alignment's panorama to pano_size):
    # area (OpenCV INTER_AREA, the default) or linear: INTER_LINEAR where a side shrinks by less than 2x (what a
    # reduced decode leaves; 6x cheaper at CVUSA's 375 -> 288, and as close to the full decode's area resize),
    # INTER_AREA beyond (transforms.resize)
    resize_interpolation: str = "area"
    # train: keep every decoded image in memory after its first read (geoloc/data/decoded.py): the same items, without
    # decoding each file again every epoch; each loader process holds its own copy (H x W x 3 bytes an image)
    cache_decoded: bool = False
    max_train: int = 0  # 0 = all; for quick runs (one-to-one splits keep their pairs; others cut the queries)
    max_val: int = 0
    calibration_holdout: int = 0  # N train queries spread over the split: kept out of training, they fit the confidence

    def __post_init__(self):
        if self.alignment not in ALIGNMENTS:
            raise ValueError(f"dataset.alignment must be one of {ALIGNMENTS}, got {self.alignment!r}")
        if self.resize_interpolation not in INTERPOLATIONS:
            raise ValueError(f"dataset.resize_interpolation must be one of {INTERPOLATIONS}, got "
                             f"{self.resize_interpolation!r}")
        for key in ("ground_extent_m", "camera_height_m"):  # at the parse, not at the first item of a run
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"dataset.{key} must be a finite number of metres > 0 (the ground projection of "
                                 f"dataset.alignment=ground), got {value}")
        if self.batch_size < 1:
            raise ValueError(f"dataset.batch_size must be >= 1, got {self.batch_size}")
        if self.aerial_size < 16 or len(self.pano_size) != 2 or min(self.pano_size) < 8:
            raise ValueError(f"image sizes too small: aerial_size={self.aerial_size}, pano_size={self.pano_size}")
        check_fov(self.fov, "dataset.fov")
        if not 0.0 <= self.aerial_rotation_deg <= 180.0:
            raise ValueError(f"dataset.aerial_rotation_deg must be in [0, 180] (a rotation of U(-r, r) degrees), "
                             f"got {self.aerial_rotation_deg}")
        if self.calibration_holdout < 0:
            raise ValueError(f"dataset.calibration_holdout must be >= 0 (train queries kept out of training to fit "
                             f"the confidence; 0: none, the gallery is uncalibrated), got {self.calibration_holdout}")
        if self.heading_steps < 1:
            raise ValueError(f"dataset.heading_steps must be >= 1 (candidate headings per query), got "
                             f"{self.heading_steps}")

    @property
    def limited_view(self) -> bool:
        """Whether query views differ from the north-aligned full panorama (a narrower fov or a random heading)."""
        return self.fov < 360.0 or self.random_heading


SHARED_KEYS = tuple(f.name for f in fields(CrossViewDataConfig))


def parse_dataset(section) -> tuple[CrossViewDataConfig, dict]:
    """A dataset section (a DictConfig, a dict, or a CrossViewDataConfig whose reader takes its defaults) -> (its
    shared keys, checked, as a CrossViewDataConfig; the reader's section: `name`, `module` and the reader's own keys,
    checked against the reader's signature). Nothing is read."""
    if isinstance(section, CrossViewDataConfig):
        section = asdict(section)
    params = OmegaConf.to_container(section, resolve=True) if isinstance(section, DictConfig) else dict(section)
    data = checked({k: v for k, v in params.items() if k in SHARED_KEYS}, CrossViewDataConfig, "dataset")
    reader = {"name": data.name, "module": data.module,
              **{k: v for k, v in params.items() if k not in SHARED_KEYS}}
    registry.check("dataset", reader)
    return data, reader
