"""Builds MMDIP's networks from config, and the generator input of each variant.

Phase 1's network is a registered `segmenter` (the kind is declared here): a factory taking `num_classes` and its
own keys, returning a module that maps B×3×H×W images to B×num_classes×H×W logits. `task.segmentation.model`
names it, `task.segmentation.module` imports a plug-in's, and `task.segmentation.<segmenter>.<key>` sets its keys.
Built-ins: erfnet (the paper's), fcn and unet (the Table I baselines).

Generator inputs (K = num_classes, images in [-1, 1]):
  ssggnet     gray(dynamic) copied K times ⊕ S (softmax of the segmentation), 2K channels (paper);
  ssggnet_sm  gray(dynamic) copied K times ⊕ onehot(M) (argmax), 2K channels;
  pix2pix     the dynamic RGB image, 3 channels;
  mgan        the dynamic RGB image ⊕ the dynamic-object mask, 4 channels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from geoloc import registry
from geoloc.models.erfnet import ERFNet
from geoloc.models.fcn import FCN8s
from geoloc.models.patchgan import PatchGAN
from geoloc.models.unet import UNet
from geoloc.tasks.mmdip.mmdip_config import SegmentationConfig, TranslationConfig

registry.declare("segmenter", section="task.segmentation", name_key="task.segmentation.model", runtime=("num_classes",))


@registry.register("segmenter", "erfnet")
def erfnet(num_classes: int) -> ERFNet:
    return ERFNet(num_classes)


@registry.register("segmenter", "fcn")
def fcn(num_classes: int, width: int = 32) -> FCN8s:
    return FCN8s(num_classes, width=width)


@registry.register("segmenter", "unet")
def unet(num_classes: int, num_downs: int = 5, ngf: int = 32) -> UNet:
    """num_downs: depth (H, W multiples of 2^num_downs)."""
    return UNet(3, num_classes, num_downs=num_downs, ngf=ngf, final=None, dropout=False)


def build_segmenter(cfg: SegmentationConfig, num_classes: int) -> nn.Module:
    """The segmenter task.segmentation.model names, with its keys: B×3×H×W images -> B×num_classes×H×W logits."""
    registry.import_module(cfg.module, "task.segmentation")
    return registry.build("segmenter", cfg.section(cfg.model), where=f"task.segmentation.{cfg.model}",
                          num_classes=num_classes)


def generator_channels(variant: str, num_classes: int) -> int:
    return {"ssggnet": 2 * num_classes, "ssggnet_sm": 2 * num_classes, "pix2pix": 3, "mgan": 4}[variant]


def build_generator(cfg: TranslationConfig, num_classes: int) -> UNet:
    return UNet(generator_channels(cfg.variant, num_classes), 3, num_downs=cfg.num_downs, ngf=cfg.ngf)


def build_discriminator(cfg: TranslationConfig) -> PatchGAN:
    return PatchGAN(6, ndf=cfg.ndf, n_layers=cfg.d_layers)  # static ⊕ dynamic


def to_signed(x: torch.Tensor) -> torch.Tensor:
    """[0, 1] -> [-1, 1]."""
    return x * 2 - 1


def generator_input(variant: str, dynamic: torch.Tensor, logits: torch.Tensor | None,
                    mask: torch.Tensor | None) -> torch.Tensor:
    """dynamic: B x 3 x H x W in [0, 1]; logits: B x K x H x W; mask: B x 1 x H x W in {0, 1}."""
    if variant == "pix2pix":
        return to_signed(dynamic)
    if variant == "mgan":
        return torch.cat([to_signed(dynamic), to_signed(mask)], 1)
    k = logits.shape[1]
    gray = to_signed(0.299 * dynamic[:, 0:1] + 0.587 * dynamic[:, 1:2] + 0.114 * dynamic[:, 2:3])
    if variant == "ssggnet":
        sem = logits.softmax(1)
    elif variant == "ssggnet_sm":
        sem = F.one_hot(logits.argmax(1), k).permute(0, 3, 1, 2).to(dynamic.dtype)
    else:
        raise ValueError(f"unknown generator variant {variant!r}")
    return torch.cat([gray.expand(-1, k, -1, -1), sem], 1)
