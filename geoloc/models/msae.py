"""Multi-scale attention encoder (MSAE) head, and the plain head of the "w/o MSAE" ablation.

Li, Tu, Chen, Yu, "Multi-scale attention encoder for street-to-aerial image geo-localization", CAAI TIT 2023:
intermediate VGG16 maps are brought to one size and concatenated; parallel 3x3/5x5/7x7 convolutions (eq. 3)
see the scene at several receptive fields; a 1x1 convolution turns their concatenation into a one-channel
attention mask that re-weights the features; an FC layer maps them to the L2-normalised descriptor.

The FC input is kept small by a 1x1 projection and average pooling to a fixed grid (a full-resolution flatten at
288x288 would need a 1.7e9-parameter FC); the grid keeps the spatial layout that cross-view matching relies on.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class _Descriptor(nn.Module):
    """1x1 projection → average pool to pool×pool → FC → L2 norm. Input B×C×h×w, output B×dim."""

    def __init__(self, in_channels: int, dim: int, proj_channels: int, pool: int):
        super().__init__()
        self.pool = pool
        self.proj = nn.Conv2d(in_channels, proj_channels, kernel_size=1)
        self.fc = nn.Linear(proj_channels * pool * pool, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.adaptive_avg_pool2d(F.relu(self.proj(x)), self.pool)
        return F.normalize(self.fc(x.flatten(1)), dim=1)


class MSAEHead(nn.Module):
    """Input: the conv3_3, conv4_3, conv5_3 maps. Output: B×dim descriptor (and the B×1×h×w mask on request)."""

    def __init__(self, in_channels: list[int], dim: int, scale_channels: int = 64, proj_channels: int = 64,
                 pool: int = 8):
        super().__init__()
        c = sum(in_channels)
        # eq. 3: three receptive fields in parallel, with bias, concatenated
        self.scales = nn.ModuleList(nn.Conv2d(c, scale_channels, k, padding=k // 2) for k in (3, 5, 7))
        self.to_mask = nn.Conv2d(3 * scale_channels, 1, kernel_size=1)
        self.descriptor = _Descriptor(c, dim, proj_channels, pool)

    def forward(self, taps: list[torch.Tensor], return_attention: bool = False):
        size = taps[-1].shape[-2:]
        # area pooling brings the finer maps down to conv5_3's grid without aliasing
        x = torch.cat([F.adaptive_avg_pool2d(t, size) if t.shape[-2:] != size else t for t in taps], dim=1)
        multi = torch.cat([F.relu(conv(x)) for conv in self.scales], dim=1)
        mask = torch.sigmoid(self.to_mask(multi))
        mask = F.interpolate(mask, size=x.shape[-2:], mode="bilinear", align_corners=False)
        desc = self.descriptor(x * mask)
        return (desc, mask) if return_attention else desc


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
