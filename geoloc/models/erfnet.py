"""ERFNet (Romera et al., T-ITS 2018): the static-segmentation network of MMDIP.

Encoder: two downsampler blocks (3x3 stride-2 conv concatenated with a max-pool), 5 non-bottleneck-1D blocks at
64 channels, a third downsampler, then 2 x 4 non-bt-1D blocks at 128 channels with dilations 2, 4, 8, 16.
Decoder: transposed-conv upsamplers to 64 and 16 channels, two non-bt-1D blocks each, and a 2x2 transposed conv
to the classes. About 2.06M parameters for 8 classes. Returns logits B x C x H x W (H, W multiples of 8); the
softmax map S and argmax M of the paper are `logits.softmax(1)` and `logits.argmax(1)`.

Weights saved by the authors' code (erfnet_pytorch's `Net`) load after `reference_state_dict` renames their keys:
`model.load_state_dict(reference_state_dict(torch.load(path)))`.
"""

from __future__ import annotations

import re

import torch
import torch.nn.functional as F
from torch import nn


class Downsampler(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout - cin, 3, stride=2, padding=1, bias=True)
        self.pool = nn.MaxPool2d(2, stride=2)
        self.bn = nn.BatchNorm2d(cout, eps=1e-3)

    def forward(self, x):
        return F.relu(self.bn(torch.cat([self.conv(x), self.pool(x)], 1)))


class NonBottleneck1D(nn.Module):
    """Residual block of factorised 3x1 / 1x3 convolutions; the second pair is dilated.

    x -> conv3x1_1 -> ReLU -> conv1x3_1 -> bn1 -> ReLU -> conv3x1_2 -> ReLU -> conv1x3_2 -> bn2 -> dropout,
    then ReLU(that + x), as in Romera et al.'s released erfnet.py (same parameter names).
    """

    def __init__(self, ch: int, dropout: float, dilation: int):
        super().__init__()
        d = dilation
        self.conv3x1_1 = nn.Conv2d(ch, ch, (3, 1), padding=(1, 0), bias=True)
        self.conv1x3_1 = nn.Conv2d(ch, ch, (1, 3), padding=(0, 1), bias=True)
        self.bn1 = nn.BatchNorm2d(ch, eps=1e-3)
        self.conv3x1_2 = nn.Conv2d(ch, ch, (3, 1), padding=(d, 0), dilation=(d, 1), bias=True)
        self.conv1x3_2 = nn.Conv2d(ch, ch, (1, 3), padding=(0, d), dilation=(1, d), bias=True)
        self.bn2 = nn.BatchNorm2d(ch, eps=1e-3)
        self.dropout = nn.Dropout2d(dropout) if dropout > 0 else nn.Identity()

    def forward(self, x):
        # the reference order: no ReLU between conv1x3 and its BN (one there changes the function once BN holds
        # trained statistics, so official weights would compute something else)
        y = self.bn1(self.conv1x3_1(F.relu(self.conv3x1_1(x))))
        y = F.relu(self.conv3x1_2(F.relu(y)))
        y = self.dropout(self.bn2(self.conv1x3_2(y)))
        return F.relu(y + x)


class Upsampler(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv = nn.ConvTranspose2d(cin, cout, 3, stride=2, padding=1, output_padding=1, bias=True)
        self.bn = nn.BatchNorm2d(cout, eps=1e-3)

    def forward(self, x):
        return F.relu(self.bn(self.conv(x)))


class ERFNet(nn.Module):
    """ERFNet(num_classes): B x 3 x H x W image -> B x num_classes x H x W logits."""

    def __init__(self, num_classes: int, in_channels: int = 3):
        super().__init__()
        enc = [Downsampler(in_channels, 16), Downsampler(16, 64)]
        enc += [NonBottleneck1D(64, 0.03, 1) for _ in range(5)]
        enc += [Downsampler(64, 128)]
        enc += [NonBottleneck1D(128, 0.3, d) for _ in range(2) for d in (2, 4, 8, 16)]
        self.encoder = nn.Sequential(*enc)
        self.decoder = nn.Sequential(
            Upsampler(128, 64), NonBottleneck1D(64, 0, 1), NonBottleneck1D(64, 0, 1),
            Upsampler(64, 16), NonBottleneck1D(16, 0, 1), NonBottleneck1D(16, 0, 1),
        )
        self.head = nn.ConvTranspose2d(16, num_classes, 2, stride=2, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if h % 8 or w % 8:
            raise ValueError(f"ERFNet needs H and W divisible by 8, got {h}x{w}")
        return self.head(self.decoder(self.encoder(x)))


def reference_state_dict(state: dict) -> dict:
    """Rename a state dict of erfnet_pytorch's `Net` (optionally saved from DataParallel) to ERFNet's keys.

    encoder.initial_block -> encoder.0, encoder.layers.i -> encoder.{i+1}, decoder.layers.i -> decoder.i,
    decoder.output_conv -> head. encoder.output_conv (the encoder-only pre-training head, unused by the full
    network) is dropped. Keys that fit none of these are kept, so load_state_dict names them.
    """
    renamed = {}
    for key, value in state.items():
        key = key.removeprefix("module.")
        if key.startswith("encoder.output_conv."):
            continue
        key = re.sub(r"^encoder\.initial_block\.", "encoder.0.", key)
        key = re.sub(r"^encoder\.layers\.(\d+)\.", lambda m: f"encoder.{int(m.group(1)) + 1}.", key)
        key = re.sub(r"^decoder\.layers\.(\d+)\.", r"decoder.\1.", key)
        key = re.sub(r"^decoder\.output_conv\.", "head.", key)
        renamed[key] = value
    return renamed
