"""vgg16_features_as_torchvision builds VGG16's layers as torchvision's constructor does, draw for draw: the same
trunk weights and the same generator state afterwards as the trunk cut from torchvision's whole VGG16, so every
seed's figures stay."""

from __future__ import annotations

import pytest
import torch
import torchvision
from geoloc.models import vgg


def cut_from_torchvision(batchnorm: bool) -> torch.nn.Sequential:
    """How geoloc built the layers before: torchvision's whole VGG16, its classifier drawn and dropped."""
    return (torchvision.models.vgg16_bn if batchnorm else torchvision.models.vgg16)(weights=None).features


def built(width: float, batchnorm: bool, seed: int):
    torch.manual_seed(seed)
    trunk = vgg.VGG16Trunk(width=width, batchnorm=batchnorm)
    return trunk, torch.get_rng_state(), torch.randn(3)  # the state after, and what is drawn next


@pytest.mark.parametrize("width,batchnorm", [(1.0, False), (0.125, True)])  # the paper's trunk, the default's
def test_the_trunk_and_the_generator_after_it_are_torchvisions(width, batchnorm, monkeypatch):
    own, own_state, own_next = built(width, batchnorm, seed=3)
    monkeypatch.setattr(vgg, "vgg16_features_as_torchvision", cut_from_torchvision)
    reference, reference_state, reference_next = built(width, batchnorm, seed=3)
    assert str(own) == str(reference)  # the same modules at the same indices
    assert own.taps == reference.taps and own.channels == reference.channels
    ours, theirs = own.state_dict(), reference.state_dict()
    assert ours.keys() == theirs.keys()
    for key, value in theirs.items():
        assert torch.equal(ours[key], value), key
    assert torch.equal(own_state, reference_state)
    assert torch.equal(own_next, reference_next)
