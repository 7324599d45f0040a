"""Building a network whose every weight is about to be loaded, without drawing its random initial weights.

A VGG16 trunk draws the weights of VGG16's whole classifier too (vgg.py, vgg16_features_as_torchvision): its
124M weights are drawn twice (the layer's own init, then VGG's) and thrown away, about 2 s a trunk on one CPU
core, 4 s for the two branches. Training keeps that draw: the generator's state after it decides every weight
drawn later, so a seed's figures depend on it. A network restored from a checkpoint does not need it:
evaluate.py, the apps and `geoloc bench` overwrite every parameter and buffer with the checkpoint's (a strict
load), and nothing in geoloc draws from the global generator after the build (datasets and samplers use their own
seeded generators).

Inside `unfilled_init()`, torch.nn.init's random fills leave their tensor as it was allocated (uninitialised
memory): the layers are built with every shape, buffer and constant as usual, and must not be used before their
weights are loaded. Initialisers outside torch.nn.init (timm's trunc_normal_) still draw.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from torch.nn import init

RANDOM_FILLS = ("uniform_", "normal_", "trunc_normal_", "kaiming_uniform_", "kaiming_normal_", "xavier_uniform_",
                "xavier_normal_", "orthogonal_", "sparse_")


def _unfilled(tensor, *args, **kwargs):
    return tensor


@contextlib.contextmanager
def unfilled_init() -> Iterator[None]:
    """torch.nn.init's random fills as no-ops for the duration, process-wide (a network another thread builds
    meanwhile is left unfilled too); restored on exit, also after an error."""
    saved = {name: getattr(init, name) for name in RANDOM_FILLS}
    try:
        for name in RANDOM_FILLS:
            setattr(init, name, _unfilled)
        yield
    finally:
        for name, fill in saved.items():
            setattr(init, name, fill)
