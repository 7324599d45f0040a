"""A refiner plug-in: the query pooled to one vector, dotted with the tile's map at each cell (no shift search),
the same map for every heading bin. Built through the registry from tests/plugins/conf/refiner/dot_map.yaml."""

import torch
import torch.nn.functional as F
from geoloc.models.refiners import Refinement
from geoloc.registry import register
from torch import nn


class DotMap(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.heading_bins = 4
        self.query_encoder = nn.Conv2d(3, channels, 3, stride=2, padding=1)
        self.reference_encoder = nn.Conv2d(3, channels, 3, stride=2, padding=1)

    def encode_query(self, images):
        return self.query_encoder(images).mean((2, 3))  # B x C

    def encode_reference(self, images):
        return self.reference_encoder(images)  # B x C x n x n

    def match(self, query, reference, headings_deg):
        headings = torch.as_tensor(headings_deg, dtype=torch.float32).reshape(-1)
        scores = torch.einsum("bc,bchw->bhw", query, reference)[:, None].expand(-1, headings.numel(), -1, -1)
        b = scores.shape[0]
        return Refinement(F.log_softmax(scores.reshape(b, -1), 1).reshape(scores.shape), headings)

    def forward(self, query, reference, headings_deg):
        return self.match(self.encode_query(query), self.encode_reference(reference), headings_deg)


@register("refiner", "dot_map")
def dot_map(channels: int = 4) -> DotMap:
    return DotMap(channels)
