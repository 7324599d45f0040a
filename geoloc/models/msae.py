"""Multi-scale attention encoder (MSAE) head, and the plain head of the "w/o MSAE" ablation.

Li, Tu, Chen, Yu, "Multi-scale attention encoder for street-to-aerial image geo-localization", CAAI TIT 2023:
intermediate VGG16 maps are brought to one size and concatenated; parallel 3x3/5x5/7x7 convolutions (eq. 3)
see the scene at several receptive fields; a 1x1 convolution turns their concatenation into a one-channel
attention mask that re-weights the features; an FC layer maps them to the L2-normalised descriptor.

Eq. 3 is s = ∪_p (k_p(d) + c): the branches' outputs are concatenated as they are, with no activation
(`scale_activation="none"`, the paper configs). `scale_activation="relu"` ends each branch in a ReLU: geoloc's
choice, the default of the head, of the CPU recipe and of every checkpoint whose config does not name it (they were
trained with it).

The FC input is kept small by a 1x1 projection and average pooling to a fixed grid (a full-resolution flatten at
288x288 would need a 1.7e9-parameter FC); the grid keeps the spatial layout that cross-view matching relies on.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


SCALE_ACTIVATIONS = ("relu", "none")


class _Descriptor(nn.Module):
    """1x1 projection → average pool to pool×pool → FC → L2 norm. Input B×C×h×w, output B×dim."""

    def __init__(self, in_channels: int, dim: int, proj_channels: int, pool: int):
        super().__init__()
        self.pool = pool
        self.proj = nn.Conv2d(in_channels, proj_channels, kernel_size=1)
        self.fc = nn.Linear(proj_channels * pool * pool, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pooled(self.local(x))

    def local(self, x: torch.Tensor) -> torch.Tensor:
        """B×proj_channels×h×w: the projected map, before the pooling."""
        return F.relu(self.proj(x))

    def pooled(self, local: torch.Tensor) -> torch.Tensor:
        x = F.adaptive_avg_pool2d(local, self.pool)
        return F.normalize(self.fc(x.flatten(1)), dim=1)


class MSAEHead(nn.Module):
    """Input: the conv3_3, conv4_3, conv5_3 maps. Output: B×dim descriptor (and the B×1×h×w mask on request).

    `features(taps)` -> (descriptor, B×proj_channels×h×w map before the pooling, mask), the same descriptor."""

    def __init__(self, in_channels: list[int], dim: int, scale_channels: int = 64, proj_channels: int = 64,
                 pool: int = 8, scale_activation: str = "relu"):
        super().__init__()
        if scale_activation not in SCALE_ACTIVATIONS:
            raise ValueError(f"head.scale_activation must be one of {SCALE_ACTIVATIONS} (none: the paper's eq. 3), "
                             f"got {scale_activation!r}")
        c = sum(in_channels)
        # eq. 3: three receptive fields in parallel, with bias, concatenated
        self.scales = nn.ModuleList(nn.Conv2d(c, scale_channels, k, padding=k // 2) for k in (3, 5, 7))
        self.scale_activation = scale_activation
        self.to_mask = nn.Conv2d(3 * scale_channels, 1, kernel_size=1)
        self.descriptor = _Descriptor(c, dim, proj_channels, pool)

    def forward(self, taps: list[torch.Tensor], return_attention: bool = False):
        x, mask = self._attended(taps)
        desc = self.descriptor(x * mask)
        return (desc, mask) if return_attention else desc

    def features(self, taps: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x, mask = self._attended(taps)
        local = self.descriptor.local(x * mask)
        return self.descriptor.pooled(local), local, mask

    def _attended(self, taps: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """(the maps at conv5_3's grid, concatenated: B×C×h×w; the attention mask B×1×h×w)."""
        size = taps[-1].shape[-2:]
        # area pooling brings the finer maps down to conv5_3's grid without aliasing
        x = torch.cat([F.adaptive_avg_pool2d(t, size) if t.shape[-2:] != size else t for t in taps], dim=1)
        if self.scale_activation == "relu":
            multi = torch.cat([F.relu(conv(x)) for conv in self.scales], dim=1)
        else:
            multi = torch.cat([conv(x) for conv in self.scales], dim=1)
        mask = torch.sigmoid(self.to_mask(multi))
        mask = F.interpolate(mask, size=x.shape[-2:], mode="bilinear", align_corners=False)
        return x, mask


class PlainHead(nn.Module):
    """The "w/o MSAE" ablation: conv5_3 only, straight to the FC descriptor, no attention."""

    def __init__(self, in_channels: list[int], dim: int, proj_channels: int = 64, pool: int = 8, **_):
        super().__init__()
        self.descriptor = _Descriptor(in_channels[-1], dim, proj_channels, pool)

    def forward(self, taps: list[torch.Tensor], return_attention: bool = False):
        desc = self.descriptor(taps[-1])
        if return_attention:
            return desc, torch.ones_like(taps[-1][:, :1])
        return desc

    def features(self, taps: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, None]:
        """(descriptor, B×proj_channels×h×w map before the pooling, no attention)."""
        local = self.descriptor.local(taps[-1])
        return self.descriptor.pooled(local), local, None
