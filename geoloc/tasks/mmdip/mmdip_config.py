"""Config schemas of the MMDIP task (`task=mmdip`) and its datasets, checked at start-up.

The `task` section holds the method (phase 1 segmentation, phase 2 translation, VPR coding); the `dataset`
section says where the images come from. Unknown keys and bad values raise geoloc.config.ConfigError.

Three parts are registered components with keys of their own, which parse_sections checks against their factories'
signatures: the segmenter (`task.segmentation.model`, its keys under `task.segmentation.<segmenter>`), the generator
loss (`task.translation.generator_loss`, a section with `name`) and the dataset reader (`dataset.name`, its keys
beside the shared ones). networks.py, generator_loss.py and readers.py declare the kinds; the package imports them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from omegaconf import DictConfig, OmegaConf

from geoloc import registry
from geoloc.config import ConfigError, checked
from geoloc.engine import TrainerConfig

VARIANTS = ("ssggnet", "ssggnet_sm", "pix2pix", "mgan")


@dataclass
class SegmentationConfig:
    """Phase 1: the static-segmentation network alone. The defaults are CPU-sized (experiment=paper_mmdip: ERFNet,
    Adam lr 2e-3, batch 1)."""

    model: str = "erfnet"  # a registered segmenter: erfnet | fcn | unet (the Table I baselines) | a plug-in's
    module: str | None = None  # a plug-in segmenter's module (docs/extending.md)
    epochs: int = 6  # paper_mmdip: 100 (geoloc's choice; the paper gives none)
    batch_size: int = 4  # paper: 1
    lr: float = 2e-3
    class_weight_formula: str = "paper"  # paper (eq. 1) | authors (1/ln(100 r + 1.02))
    # {segmenter: its own keys}, written task.segmentation.<segmenter>.<key> (e.g. unet.num_downs); task_config()
    # fills it, parse_sections checks each against that segmenter's signature
    segmenter_keys: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if self.epochs < 1 or self.batch_size < 1 or self.lr <= 0:
            raise ValueError("task.segmentation.epochs and batch_size must be >= 1 and lr > 0")

    def section(self, name: str) -> dict:
        """The registry section of segmenter `name`: its name and its own keys."""
        return {"name": name, **self.segmenter_keys.get(name, {})}


@dataclass
class TranslationConfig:
    """Phase 2: segmentation + U-Net generator + PatchGAN, end to end (paper: lrs 1e-4 / 2e-3 / 4e-3, batch 4). The
    network sizes are CPU-sized (experiment=paper_mmdip: the pix2pix U-Net 256, ngf = ndf = 64)."""

    variant: str = "ssggnet"  # ssggnet (gray x K + S) | ssggnet_sm (gray x K + onehot(M)) | pix2pix | mgan
    epochs: int = 6  # paper_mmdip: 100
    batch_size: int = 4
    lr_seg: float = 1e-4
    lr_g: float = 2e-3
    lr_d: float = 4e-3
    beta1: float = 0.5  # Adam beta1 of G and D, as in pix2pix
    # a registered generator loss and its keys: pix2pix (adv 1, L1 100, perceptual 10) | paper (eq. 2: 1, 1, 1)
    generator_loss: dict[str, Any] = field(default_factory=lambda: {"name": "pix2pix"})
    lambda_seg: float = 1.0  # weighted cross-entropy keeps the segmentation static while G trains through it
    perceptual_weights: str = "none"  # imagenet (torch hub cache) | /path/to/vgg16.pth | none (random, CPU smoke)
    perceptual_layers: list[str] = field(default_factory=lambda: ["relu1_2", "relu2_2", "relu3_3"])
    num_downs: int = 5  # U-Net depth; pix2pix at 256 x 256: 8
    ngf: int = 32  # pix2pix: 64
    ndf: int = 32  # pix2pix: 64
    d_layers: int = 3
    init_from_phase1: bool = True

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"task.translation.variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.epochs < 1 or self.batch_size < 1 or min(self.lr_seg, self.lr_g, self.lr_d) <= 0:
            raise ValueError("task.translation.epochs and batch_size must be >= 1 and learning rates > 0")


@dataclass
class VPRConfig:
    """Coding and retrieval: ORB BoW of the recovered image, SPM of the static segmentation, eq. 5 fusion."""

    levels: int = 2
    alpha: float = 0.5
    vocab_size: int = 1000
    vocab_iters: int = 10
    orb_features: int = 500
    orb_patch_size: int = 31
    orb_fast_threshold: int = 20
    gallery_seg: str = "predicted"  # predicted (segment the reference's static image) | label (ground truth)
    ks: list[int] = field(default_factory=lambda: [1, 5, 10])

    def __post_init__(self):
        if not 0 <= self.alpha <= 1:
            raise ValueError(f"task.vpr.alpha must lie in [0, 1], got {self.alpha}")
        if not 0 <= self.levels <= 8:
            raise ValueError(f"task.vpr.levels must lie in 0..8, got {self.levels}")
        if self.gallery_seg not in ("predicted", "label"):
            raise ValueError(f"task.vpr.gallery_seg must be 'predicted' or 'label', got {self.gallery_seg!r}")
        if self.vocab_size < 2:
            raise ValueError("task.vpr.vocab_size must be >= 2")


@dataclass
class MMDIPConfig:
    name: str = "mmdip"
    num_classes: int = 8
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    translation: TranslationConfig = field(default_factory=TranslationConfig)
    vpr: VPRConfig = field(default_factory=VPRConfig)

    def __post_init__(self):
        if self.name != "mmdip":
            raise ValueError(f"task.name must be 'mmdip', got {self.name!r}")


@dataclass
class DynamicDataConfig:
    """The keys every dynamic-scene dataset shares. The reader's own keys (the synthetic layout's `preset`,
    `train_size`...) go to the reader registered under `name` (readers.py), which checks them against its
    signature; data_config() keeps them in `reader_keys`."""

    name: str = "dynamic"  # a registered reader: dynamic (synthetic layout) | carla4 | emptycities | a plug-in's
    module: str | None = None  # a plug-in reader's module (docs/extending.md)
    root: str | None = None  # dynamic: null = generate the synthetic layout on first use into the cache
    split: str | None = "val"  # the split scored; emptycities: null = the images directly under root
    image_size: list[int] = field(default_factory=lambda: [128, 128])  # H, W every image is brought to
    val_batch_size: int = 8
    augment: bool = True  # horizontal flips in training
    check_files: str = "exists"  # decode | exists | off
    reader_keys: dict[str, Any] = field(default_factory=dict)  # dataset.<key> beyond the ones above

    def __post_init__(self):
        if len(self.image_size) != 2 or min(self.image_size) < 16 or any(s % 8 for s in self.image_size):
            raise ValueError(f"dataset.image_size must be [H, W], multiples of 8 and >= 16, got {self.image_size}")

    def reader_section(self) -> dict:
        """The registry section of the reader: its name, module and own keys."""
        return {"name": self.name, "module": self.module, **self.reader_keys}


SEGMENTATION_KEYS = tuple(f.name for f in fields(SegmentationConfig) if f.name != "segmenter_keys")
SHARED_DATA_KEYS = tuple(f.name for f in fields(DynamicDataConfig) if f.name != "reader_keys")


def _plain(section) -> dict:
    return OmegaConf.to_container(section, resolve=True) if isinstance(section, DictConfig) else dict(section or {})


def parse_sections(cfg: DictConfig) -> tuple[MMDIPConfig, DynamicDataConfig, TrainerConfig]:
    """train.py's task, dataset and trainer sections, checked, and every registered part they name checked against
    the registry: the segmenter and each task.segmentation.<segmenter> given, the generator loss, and the reader,
    which must have labels to train on."""
    task, data = _task_section(cfg.task), _data_section(cfg.dataset)
    task_cfg, data_cfg = checked(task, MMDIPConfig, "task"), checked(data, DynamicDataConfig, "dataset")
    trainer_cfg = checked(cfg.trainer, TrainerConfig, "trainer")
    seg = task_cfg.segmentation
    registry.import_module(seg.module, "task.segmentation")
    registry.lookup("segmenter", seg.model)
    for name in seg.segmenter_keys:
        if name not in registry.names("segmenter"):
            raise ConfigError(f"task.segmentation.{name} is neither a key of task.segmentation nor a registered "
                              f"segmenter ({registry.names('segmenter')}); a segmenter's own keys go under "
                              f"task.segmentation.<segmenter>")
    for name in dict.fromkeys([seg.model, *seg.segmenter_keys]):
        registry.check("segmenter", seg.section(name), where=f"task.segmentation.{name}")
    registry.check("generator_loss", task_cfg.translation.generator_loss)
    registry.check("mmdip_dataset", data_cfg.reader_section())
    if getattr(registry.find("mmdip_dataset", data_cfg.reader_section()), "evaluation_only", False):
        raise ConfigError(f"dataset={data_cfg.name} has no labels: it is for evaluation only (evaluate.py ckpt=...)")
    return task_cfg, data_cfg, trainer_cfg


def task_config(section) -> MMDIPConfig:
    """The `task` section, checked; each task.segmentation.<segmenter> sub-section goes to segmenter_keys."""
    return checked(_task_section(section), MMDIPConfig, "task")


def data_config(section) -> DynamicDataConfig:
    """The `dataset` section, checked: the shared keys here, the reader's own kept in reader_keys (readers.py
    checks them against the reader's signature when it builds the reader)."""
    return checked(_data_section(section), DynamicDataConfig, "dataset")


def _task_section(section) -> dict:
    task = _plain(section)
    segmentation = _plain(task.get("segmentation"))
    own = {k: segmentation.pop(k) for k in list(segmentation) if k not in SEGMENTATION_KEYS}
    for key, value in own.items():
        if not isinstance(value, dict):
            raise ConfigError(f"task.segmentation.{key} is not a key of task.segmentation (its keys are "
                              f"{list(SEGMENTATION_KEYS)}); a segmenter's own keys go under "
                              f"task.segmentation.<segmenter>.<key>, e.g. task.segmentation.unet.num_downs")
    if "segmentation" in task:
        task["segmentation"] = {**segmentation, "segmenter_keys": own}
    return task


def _data_section(section) -> dict:
    data = _plain(section)
    shared = {k: v for k, v in data.items() if k in SHARED_DATA_KEYS}
    return {**shared, "reader_keys": {k: v for k, v in data.items() if k not in SHARED_DATA_KEYS}}
