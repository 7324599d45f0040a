"""Builds MMDIP's networks from config, and the generator input of each variant.

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
from geoloc.tasks.mmdip.config import SegmentationConfig, TranslationConfig

registry.declare("segmenter", section="task.segmentation", name_key="task.segmentation.model")


@registry.register("segmenter", "erfnet")
def erfnet(num_classes: int) -> ERFNet:
    return ERFNet(num_classes)


@registry.register("segmenter", "fcn")
def fcn(num_classes: int, fcn_width: int = 32) -> FCN8s:
    return FCN8s(num_classes, width=fcn_width)


@registry.register("segmenter", "unet")
def unet(num_classes: int, unet_num_downs: int = 5, unet_ngf: int = 32) -> UNet:
    return UNet(3, num_classes, num_downs=unet_num_downs, ngf=unet_ngf, final=None, dropout=False)


def segmenter_factory(cfg: SegmentationConfig):
    """The registered segmenter task.segmentation.model names (after importing task.segmentation.module)."""
    registry.import_module(cfg.module, "task.segmentation")
    return registry.lookup("segmenter", cfg.model)


def build_segmenter(cfg: SegmentationConfig, num_classes: int) -> nn.Module:
    """A segmenter maps B×3×H×W images to B×num_classes×H×W logits; it takes num_classes and, if it names them,
    the baselines' size keys of task.segmentation (fcn_width, unet_num_downs, unet_ngf)."""
    factory = segmenter_factory(cfg)
    sizes = {"fcn_width": cfg.fcn_width, "unet_num_downs": cfg.unet_num_downs, "unet_ngf": cfg.unet_ngf}
    return factory(**registry.accepted(factory, {"num_classes": num_classes, **sizes}))


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
