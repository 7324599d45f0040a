"""A head plug-in: mean and max pooling of the coarsest map, concatenated, then a linear map to `dim`."""

import torch
import torch.nn.functional as F
from geoloc.registry import register
from torch import nn


class MeanMaxHead(nn.Module):
    def __init__(self, in_channels: list[int], dim: int):
        super().__init__()
        self.fc = nn.Linear(2 * in_channels[-1], dim)

    def forward(self, maps: list[torch.Tensor], return_attention: bool = False):
        x = maps[-1]
        desc = F.normalize(self.fc(torch.cat([x.mean(dim=(2, 3)), x.amax(dim=(2, 3))], dim=1)), dim=1)
        return (desc, torch.ones_like(x[:, :1])) if return_attention else desc


@register("head", "mean_max")
def mean_max(in_channels: list[int], dim: int) -> MeanMaxHead:
    return MeanMaxHead(in_channels, dim)
