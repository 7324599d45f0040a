"""A segmenter plug-in for task=mmdip: one convolution to class logits; its own key `kernel` is set as
task.segmentation.tiny_segmenter.kernel."""

from geoloc.registry import register
from torch import nn


@register("segmenter", "tiny_segmenter")
def tiny_segmenter(num_classes: int, kernel: int = 3) -> nn.Module:
    return nn.Conv2d(3, num_classes, kernel_size=kernel, padding=kernel // 2)
