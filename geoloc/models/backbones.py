"""The registered backbones. A backbone is an nn.Module with `channels: list[int]` whose forward maps a
B×3×H×W image to multi-scale maps, fine to coarse (the heads read them; docs/extending.md). This module declares
the `backbone` kind and registers the built-ins: vgg16 here, timm in timm_backbone.py."""

from __future__ import annotations

from geoloc.models import timm_backbone  # noqa: F401  (registers "timm"; timm itself is imported on use)
from geoloc.models.vgg import VGG16Trunk
from geoloc.registry import declare, register

declare("backbone", section="backbone")


@register("backbone", "vgg16")
def vgg16(width: float = 1.0, pretrained: bool = True, weights_path: str | None = None,
          batchnorm: bool = False) -> VGG16Trunk:
    """VGG16 (or VGG16-BN) up to conv5_3, tapped at conv3_3 / conv4_3 / conv5_3 (the paper's trunk).

    width scales every layer's channels (1.0 = VGG16; the CPU default uses 0.125 from scratch); ImageNet weights are
    read offline from torchvision's hub cache or `weights_path`, never downloaded."""
    if width <= 0:
        raise ValueError(f"backbone.width must be > 0, got {width}")
    return VGG16Trunk(width, pretrained, weights_path, batchnorm)
