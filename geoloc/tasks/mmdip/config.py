"""Config schemas of the MMDIP task (`task=mmdip`) and its datasets, checked at start-up.

The `task` section holds the method (phase 1 segmentation, phase 2 translation, VPR coding); the `dataset`
section says where the images come from. Unknown keys and bad values raise geoloc.config.ConfigError.
"""

from __future__ import annotations

from dataclasses import dataclass, field

VARIANTS = ("ssggnet", "ssggnet_sm", "pix2pix", "mgan")
DATASETS = ("dynamic", "emptycities", "carla4")
# Generator loss weights (adversarial, L1, perceptual) by name: task.translation.loss_weights
GENERATOR_LOSS_WEIGHTS = {
    "paper": {"adv": 1.0, "l1": 1.0, "perceptual": 1.0},  # MMDIP eq. 2: L_G = L_adv + L_pixel + L_perceptual
    "pix2pix": {"adv": 1.0, "l1": 100.0, "perceptual": 10.0},  # pix2pix's lambda_L1 = 100; VGG term 10 (pix2pixHD)
}


@dataclass
class SegmentationConfig:
    """Phase 1: the static-segmentation network alone (paper: ERFNet, Adam lr 2e-3, batch 1)."""

    model: str = "erfnet"  # a registered segmenter: erfnet | fcn | unet (the Table I baselines) | a plug-in's
    module: str | None = None  # a plug-in segmenter's module (docs/extending.md)
    epochs: int = 20
    batch_size: int = 1
    lr: float = 2e-3
    class_weight_formula: str = "paper"  # paper (eq. 1) | authors (1/ln(100 r + 1.02))
    unet_num_downs: int = 5  # U-Net baseline depth (H, W multiples of 2^num_downs)
    unet_ngf: int = 32
    fcn_width: int = 32

    def __post_init__(self):
        if self.epochs < 1 or self.batch_size < 1 or self.lr <= 0:
            raise ValueError("task.segmentation.epochs and batch_size must be >= 1 and lr > 0")


@dataclass
class TranslationConfig:
    """Phase 2: segmentation + U-Net generator + PatchGAN, end to end (paper: lrs 1e-4 / 2e-3 / 4e-3, batch 4)."""

    variant: str = "ssggnet"  # ssggnet (gray x K + S) | ssggnet_sm (gray x K + onehot(M)) | pix2pix | mgan
    epochs: int = 20
    batch_size: int = 4
    lr_seg: float = 1e-4
    lr_g: float = 2e-3
    lr_d: float = 4e-3
    beta1: float = 0.5  # Adam beta1 of G and D, as in pix2pix
    loss_weights: str = "pix2pix"  # pix2pix (adv 1, L1 100, perceptual 10) | paper (eq. 2: 1, 1, 1)
    lambda_seg: float = 1.0  # weighted cross-entropy keeps the segmentation static while G trains through it
    perceptual_weights: str = "none"  # imagenet (torch hub cache) | /path/to/vgg16.pth | none (random, CPU smoke)
    perceptual_layers: list[str] = field(default_factory=lambda: ["relu1_2", "relu2_2", "relu3_3"])
    num_downs: int = 7  # U-Net depth: 8 for 256 x 256 as in pix2pix
    ngf: int = 64
    ndf: int = 64
    d_layers: int = 3
    init_from_phase1: bool = True

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"task.translation.variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.epochs < 1 or self.batch_size < 1 or min(self.lr_seg, self.lr_g, self.lr_d) <= 0:
            raise ValueError("task.translation.epochs and batch_size must be >= 1 and learning rates > 0")
        if self.loss_weights not in GENERATOR_LOSS_WEIGHTS:
            raise ValueError(f"task.translation.loss_weights must be one of {tuple(GENERATOR_LOSS_WEIGHTS)}, "
                             f"got {self.loss_weights!r}")

    @property
    def generator_loss_weights(self) -> dict[str, float]:
        """{'adv', 'l1', 'perceptual'} -> weight of that term of the generator loss."""
        return GENERATOR_LOSS_WEIGHTS[self.loss_weights]


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
    name: str = "dynamic"  # dynamic (synthetic layout) | carla4 (authors' 4-panel) | emptycities (3-panel, eval)
    root: str | None = None  # dynamic: null = generate the synthetic layout on first use into the cache
    split: str | None = "val"  # the split scored; emptycities: null = the images directly under root
    image_size: list[int] = field(default_factory=lambda: [128, 128])  # H, W every image is brought to
    val_batch_size: int = 8
    augment: bool = True  # horizontal flips in training
    check_files: str = "exists"  # decode | exists | off
    # synthetic only: what to generate on first use
    preset: str = "dynamic_small"
    train_size: int = 200  # places (two views each)
    val_size: int = 100
    view_size: int | None = 128  # rendered side in pixels; null = the preset's
    seed: int = 0
    workers: int = 2

    def __post_init__(self):
        if self.name not in DATASETS:
            raise ValueError(f"unknown dynamic-scene dataset {self.name!r}; choose one of {DATASETS}")
        if self.name != "dynamic" and not self.root:
            raise ValueError(f"dataset={self.name} needs dataset.root=/path/to/the/images")
        if len(self.image_size) != 2 or min(self.image_size) < 16 or any(s % 8 for s in self.image_size):
            raise ValueError(f"dataset.image_size must be [H, W], multiples of 8 and >= 16, got {self.image_size}")
