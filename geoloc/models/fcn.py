"""A small FCN-8s (Long et al. 2015) segmentation baseline for MMDIP Table I.

A slim VGG-style backbone (channels 32-64-128-256-256, two 3x3 convs per stage) trained from scratch; class
scores from pool5, pool4 and pool3 are fused with bilinear 2x, 2x and 8x upsampling, as in FCN-8s.
Returns logits B x C x H x W (H, W multiples of 32).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def _stage(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU(),
        nn.Conv2d(cout, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU(),
        nn.MaxPool2d(2),
    )


class FCN8s(nn.Module):
    def __init__(self, num_classes: int, in_channels: int = 3, width: int = 32):
        super().__init__()
        ch = [width, 2 * width, 4 * width, 8 * width, 8 * width]
        self.stages = nn.ModuleList(_stage(a, b) for a, b in zip([in_channels] + ch[:-1], ch))
        self.fc = nn.Sequential(nn.Conv2d(ch[4], 16 * width, 3, padding=1), nn.ReLU(), nn.Dropout2d(0.1))
        self.score5 = nn.Conv2d(16 * width, num_classes, 1)
        self.score4 = nn.Conv2d(ch[3], num_classes, 1)
        self.score3 = nn.Conv2d(ch[2], num_classes, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if h % 32 or w % 32:
            raise ValueError(f"FCN8s needs H and W divisible by 32, got {h}x{w}")
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        up = lambda t, ref: F.interpolate(t, size=ref.shape[-2:], mode="bilinear", align_corners=False)
        s = self.score5(self.fc(feats[4]))
        s = up(s, feats[3]) + self.score4(feats[3])
        s = up(s, feats[2]) + self.score3(feats[2])
        return F.interpolate(s, size=(h, w), mode="bilinear", align_corners=False)
