"""A backbone plug-in: two strided convolutions, returning both maps (fine to coarse)."""

import torch
from geoloc.registry import register
from torch import nn


class TinyCNN(nn.Module):
    def __init__(self, width: int):
        super().__init__()
        self.channels = [width, 2 * width]
        self.stage1 = nn.Sequential(nn.Conv2d(3, width, 3, stride=2, padding=1), nn.ReLU())
        self.stage2 = nn.Sequential(nn.Conv2d(width, 2 * width, 3, stride=2, padding=1), nn.ReLU())

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        fine = self.stage1(x)
        return [fine, self.stage2(fine)]


@register("backbone", "tiny_cnn")
def tiny_cnn(width: int = 8) -> TinyCNN:
    return TinyCNN(width)
