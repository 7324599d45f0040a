"""The cross-view Siamese: a query branch (street) and a reference branch (aerial), each a backbone + a head,
both built from config through the registry. The paper's network is two unshared VGG16 trunks with MSAE heads;
Sample4Geo shares one ConvNeXt between the views (`model.shared=true`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from geoloc import registry
from geoloc.models import backbones, heads  # noqa: F401  (declare the backbone and head kinds, register built-ins)


@dataclass
class CrossViewModelConfig:
    dim: int = 4096  # descriptor dimension, handed to the head
    shared: bool = False  # one branch for both views (Sample4Geo) instead of two unshared ones (the paper)

    def __post_init__(self):
        if self.dim < 1:
            raise ValueError(f"model.dim must be >= 1, got {self.dim}")


@dataclass
class BranchFeatures:
    """What a branch computes for one batch, beyond the descriptor: for methods that match maps (metric
    localisation inside a tile) rather than descriptors alone.

    descriptor: B×dim, L2-normalised, exactly what the branch's forward returns;
    maps: the backbone's maps, as it returns them (VGG16: conv3_3, conv4_3, conv5_3), each B×C_i×h_i×w_i;
    head_map: B×C×h×w, the head's map just before its pooling (None when the head offers none: heads.py);
    attention: B×1×h×w, the head's attention mask (MSAE), or None."""

    descriptor: torch.Tensor
    maps: list[torch.Tensor] = field(default_factory=list)
    head_map: torch.Tensor | None = None
    attention: torch.Tensor | None = None


class Branch(nn.Module):
    """A backbone and a head: forward(x) -> B×dim descriptor; features(x) -> BranchFeatures (the same descriptor,
    with the maps it came from). forward is the default path and computes the descriptor only."""

    def __init__(self, backbone: dict, head: dict, dim: int):
        super().__init__()
        self.trunk = registry.build("backbone", backbone)
        channels = getattr(self.trunk, "channels", None)
        if not channels:
            raise TypeError(f"backbone {backbone.get('name')!r} has no `channels` list; a backbone must say the "
                            "channels of the maps it returns (docs/extending.md)")
        self.head = registry.build("head", head, in_channels=list(channels), dim=dim)

    def forward(self, x: torch.Tensor, return_attention: bool = False):
        return self.head(self.trunk(x), return_attention=return_attention)

    def features(self, x: torch.Tensor) -> BranchFeatures:
        maps = list(self.trunk(x))
        if hasattr(self.head, "features"):
            descriptor, head_map, attention = self.head.features(maps)
            return BranchFeatures(descriptor, maps, head_map, attention)
        return BranchFeatures(self.head(maps), maps)


class CrossViewModel(nn.Module):
    """query: B×3×Hq×Wq street (after IPT/polar alignment) → B×dim; reference: B×3×Hr×Wr aerial → B×dim."""

    def __init__(self, backbone: dict, head: dict, cfg: CrossViewModelConfig | None = None):
        super().__init__()
        cfg = cfg or CrossViewModelConfig()
        self.shared = cfg.shared
        self.query = Branch(backbone, head, cfg.dim)
        self.reference = self.query if cfg.shared else Branch(backbone, head, cfg.dim)

    def forward(self, query: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.query(query), self.reference(reference)

    def features(self, query: torch.Tensor, reference: torch.Tensor) -> tuple[BranchFeatures, BranchFeatures]:
        """forward's descriptors with their maps (Branch.features), one BranchFeatures per view."""
        return self.query.features(query), self.reference.features(reference)

    def encoders(self, aerial_queries: bool = False) -> tuple[Branch, Branch]:
        """(the encoder of a split's queries, of its references). Each image goes through its own view's branch,
        so aerial queries (University-1652's satellite -> drone) are encoded by the reference branch."""
        return (self.reference, self.query) if aerial_queries else (self.query, self.reference)
