"""A loss plug-in: a hard-margin triplet on the hardest in-batch negative of each query, label-aware."""

import torch
from geoloc.registry import register
from torch import nn


class MarginTriplet(nn.Module):
    def __init__(self, margin: float):
        super().__init__()
        self.margin = margin

    def forward(self, query: torch.Tensor, reference: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        dist = 2 - 2 * query @ reference.t()
        same_place = labels[:, None] == labels[None, :]
        hardest = dist.masked_fill(same_place, float("inf")).amin(dim=1)
        return torch.relu(dist.diagonal() - hardest + self.margin).mean()


@register("loss", "margin_triplet")
def margin_triplet(margin: float = 0.2) -> MarginTriplet:
    return MarginTriplet(margin)
