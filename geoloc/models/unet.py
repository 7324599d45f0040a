"""U-Net encoder-decoder with skip connections (pix2pix generator, Isola et al. 2017).

`num_downs` stride-2 4x4 convolutions (channels ngf * min(2^i, 8)) and mirrored transposed convolutions with
skips. As the SSGGNet / pix2pix / MGAN generator the output is tanh (images in [-1, 1]); with `final=None` it
is the U-Net segmentation baseline of MMDIP Table I (logits). H and W must be multiples of 2^num_downs.
"""

from __future__ import annotations

import torch
from torch import nn


class UNet(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, num_downs: int = 8, ngf: int = 64,
                 final: str | None = "tanh", dropout: bool = True):
        super().__init__()
        if num_downs < 2:
            raise ValueError("UNet needs num_downs >= 2")
        if final not in ("tanh", None):
            raise ValueError(f"final must be 'tanh' or None, got {final!r}")
        self.in_channels, self.num_downs = in_channels, num_downs
        ch = [ngf * min(2**i, 8) for i in range(num_downs)]
        self.downs = nn.ModuleList()
        for i in range(num_downs):
            layers = [] if i == 0 else [nn.LeakyReLU(0.2)]
            norm = 0 < i < num_downs - 1
            layers.append(nn.Conv2d(in_channels if i == 0 else ch[i - 1], ch[i], 4, 2, 1, bias=not norm))
            if norm:
                layers.append(nn.BatchNorm2d(ch[i]))
            self.downs.append(nn.Sequential(*layers))
        self.ups = nn.ModuleList()
        for j in reversed(range(num_downs)):  # innermost first
            cin = ch[j] if j == num_downs - 1 else 2 * ch[j]
            cout = out_channels if j == 0 else ch[j - 1]
            layers = [nn.ReLU(), nn.ConvTranspose2d(cin, cout, 4, 2, 1, bias=j == 0)]
            if j > 0:
                layers.append(nn.BatchNorm2d(cout))
            if dropout and max(1, num_downs - 4) <= j < num_downs - 1:
                layers.append(nn.Dropout(0.5))
            if j == 0 and final == "tanh":
                layers.append(nn.Tanh())
            self.ups.append(nn.Sequential(*layers))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """B x in_channels x H x W -> B x out_channels x H x W."""
        m = 2**self.num_downs
        if x.shape[-1] % m or x.shape[-2] % m:
            raise ValueError(f"UNet with {self.num_downs} downs needs H, W divisible by {m}, got {tuple(x.shape[-2:])}")
        skips = []
        for down in self.downs:
            x = down(x)
            skips.append(x)
        x = self.ups[0](skips.pop())
        for up in self.ups[1:]:
            x = up(torch.cat([x, skips.pop()], 1))
        return x
