"""The registered heads. A head maps a backbone's multi-scale maps to an L2-normalised B×dim descriptor:
`head(in_channels=backbone.channels, dim=model.dim, **config)`, forward(maps, return_attention=False).

A head may also offer `features(maps) -> (descriptor, map, attention)`: the same descriptor, its B×C×h×w map just
before the pooling, and its B×1×h×w attention (None where it has none), for methods that match maps rather than
descriptors (Branch.features, models/crossview.py). A head without it gives the descriptor alone there.

This module declares the `head` kind and registers the built-ins."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from geoloc.models.msae import MSAEHead, PlainHead
from geoloc.registry import declare, register

declare("head", section="head", runtime=("in_channels", "dim"))


@register("head", "msae")
def msae(in_channels: list[int], dim: int, scale_channels: int = 64, proj_channels: int = 64,
         pool: int = 8, scale_activation: str = "relu") -> MSAEHead:
    """The paper's multi-scale attention encoder over every map the backbone gives (geoloc/models/msae.py).

    scale_activation: "none" is eq. 3 as written (geoloc/conf/head/msae.yaml, the paper configs); "relu" ends each
    multi-scale branch in a ReLU, geoloc's choice, the default here (geoloc/conf/head/msae_cpu.yaml, and every checkpoint
    whose config does not name it, since that is how they were trained)."""
    _check_sizes(dim=dim, scale_channels=scale_channels, proj_channels=proj_channels, pool=pool)
    return MSAEHead(in_channels, dim, scale_channels=scale_channels, proj_channels=proj_channels, pool=pool,
                    scale_activation=scale_activation)


@register("head", "fc")
def fc(in_channels: list[int], dim: int, proj_channels: int = 64, pool: int = 8,
       scale_channels: int | None = None, scale_activation: str | None = None) -> PlainHead:
    """The "w/o MSAE" ablation: the coarsest map only, projected, pooled to pool×pool and mapped by an FC.

    `scale_channels` and `scale_activation` (MSAE's branches) are accepted and unused, so `ablation=no_msae` can swap
    only the name of any MSAE head config and keep its projection and pooling: the ablation changes the attention,
    nothing else."""
    _check_sizes(dim=dim, proj_channels=proj_channels, pool=pool)
    return PlainHead(in_channels, dim, proj_channels=proj_channels, pool=pool)


class GlobalPoolHead(nn.Module):
    """Global average pooling of the coarsest map (Sample4Geo's descriptor), then a linear map when dim differs
    from the map's channels. Output B×dim, L2-normalised."""

    def __init__(self, in_channels: list[int], dim: int):
        super().__init__()
        channels = in_channels[-1]
        self.proj = nn.Identity() if dim == channels else nn.Linear(channels, dim)

    def forward(self, maps: list[torch.Tensor], return_attention: bool = False):
        desc = F.normalize(self.proj(maps[-1].mean(dim=(2, 3))), dim=1)
        if return_attention:
            return desc, torch.ones_like(maps[-1][:, :1])
        return desc

    def features(self, maps: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, None]:
        """(descriptor, the coarsest map it averages, no attention)."""
        return self(maps), maps[-1], None


@register("head", "gap")
def gap(in_channels: list[int], dim: int) -> GlobalPoolHead:
    _check_sizes(dim=dim)
    return GlobalPoolHead(in_channels, dim)


def _check_sizes(**sizes: int) -> None:
    bad = {k: v for k, v in sizes.items() if not isinstance(v, int) or v < 1}
    if bad:
        raise ValueError(f"head sizes must be integers >= 1, got {bad}")
