"""A segmenter plug-in for task=mmdip: one 3x3 convolution to class logits."""

from geoloc.registry import register
from torch import nn


@register("segmenter", "tiny_segmenter")
def tiny_segmenter(num_classes: int) -> nn.Module:
    return nn.Conv2d(3, num_classes, kernel_size=3, padding=1)
