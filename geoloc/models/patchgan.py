"""PatchGAN discriminator (pix2pix, Isola et al. 2017): a fully convolutional net scoring overlapping patches.

With n_layers = 3 each output cell sees a 70 x 70 patch. SSGGNet feeds it static ⊕ dynamic (6 channels).
Outputs raw scores B x 1 x h x w, for the least-squares GAN loss.
"""

from __future__ import annotations

import torch
from torch import nn


class PatchGAN(nn.Module):
    def __init__(self, in_channels: int = 6, ndf: int = 64, n_layers: int = 3):
        super().__init__()
        layers = [nn.Conv2d(in_channels, ndf, 4, 2, 1), nn.LeakyReLU(0.2)]
        ch = ndf
        for n in range(1, n_layers + 1):
            out = ndf * min(2**n, 8)
            stride = 2 if n < n_layers else 1
            layers += [nn.Conv2d(ch, out, 4, stride, 1, bias=False), nn.BatchNorm2d(out), nn.LeakyReLU(0.2)]
            ch = out
        layers.append(nn.Conv2d(ch, 1, 4, 1, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)
