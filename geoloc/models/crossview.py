"""Two unshared VGG16 branches with MSAE heads: one for street queries, one for aerial references."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from geoloc.config import require_name
from geoloc.models.msae import MSAEHead, PlainHead
from geoloc.models.vgg import VGG16Trunk


@dataclass
class CrossViewModelConfig:
    name: str = "msae_vgg16"
    width: float = 1.0  # VGG16 channel multiplier; 1.0 is the paper's network
    pretrained: bool = True  # ImageNet weights for both trunks (offline: hub cache or weights_path)
    weights_path: str | None = None
    batchnorm: bool = False  # VGG16-BN trunk: trains from scratch (the CPU default); the paper uses plain VGG16
    msae: bool = True  # false = the paper's "w/o MSAE" ablation (plain FC head)
    dim: int = 4096  # descriptor dimension
    scale_channels: int = 64
    proj_channels: int = 64
    pool: int = 8

    def __post_init__(self):
        require_name("model", self.name, ("msae_vgg16",))
        if self.width <= 0:
            raise ValueError(f"model.width must be > 0, got {self.width}")
        if self.dim < 1 or self.pool < 1 or self.proj_channels < 1 or self.scale_channels < 1:
            raise ValueError("model.dim, model.pool, model.proj_channels and model.scale_channels must be >= 1")


class Branch(nn.Module):
    def __init__(self, cfg: CrossViewModelConfig):
        super().__init__()
        self.trunk = VGG16Trunk(cfg.width, cfg.pretrained, cfg.weights_path, cfg.batchnorm)
        head = MSAEHead if cfg.msae else PlainHead
        self.head = head(self.trunk.channels, cfg.dim, scale_channels=cfg.scale_channels,
                         proj_channels=cfg.proj_channels, pool=cfg.pool)

    def forward(self, x: torch.Tensor, return_attention: bool = False):
        return self.head(self.trunk(x), return_attention=return_attention)


class CrossViewModel(nn.Module):
    """query: B×3×Hq×Wq street (after IPT/polar alignment) → B×dim; reference: B×3×Hr×Wr aerial → B×dim."""

    def __init__(self, cfg: CrossViewModelConfig):
        super().__init__()
        self.query = Branch(cfg)
        self.reference = Branch(cfg)

    def forward(self, query: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.query(query), self.reference(reference)
