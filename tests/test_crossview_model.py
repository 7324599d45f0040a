"""The two-branch VGG16 + MSAE network: shapes, independence of the branches, ablation head, weight loading."""

from __future__ import annotations

import pytest
import torch
from torchvision.models import vgg16

from geoloc.models import vgg as vgg_module
from geoloc.models.crossview import CrossViewModel, CrossViewModelConfig
from geoloc.models.vgg import MissingWeightsError, VGG16Trunk

SMALL = dict(width=0.125, pretrained=False, dim=32, scale_channels=8, proj_channels=8, pool=4)


def test_descriptors_are_l2_normalised_and_shaped():
    model = CrossViewModel(CrossViewModelConfig(**SMALL))
    q, r = model(torch.randn(2, 3, 64, 64), torch.randn(2, 3, 64, 64))
    assert q.shape == r.shape == (2, 32)
    assert torch.allclose(q.norm(dim=1), torch.ones(2), atol=1e-5)
    # a panorama-shaped query (alignment none/polar) also works
    assert model.query(torch.randn(1, 3, 32, 160)).shape == (1, 32)


def test_branches_share_no_weights():
    model = CrossViewModel(CrossViewModelConfig(**SMALL))
    q_ids = {id(p) for p in model.query.parameters()}
    assert not q_ids & {id(p) for p in model.reference.parameters()}


def test_attention_map_is_returned_and_reweights():
    model = CrossViewModel(CrossViewModelConfig(**SMALL))
    desc, mask = model.query(torch.randn(1, 3, 64, 64), return_attention=True)
    assert mask.shape == (1, 1, 4, 4) and (mask >= 0).all() and (mask <= 1).all()
    # the mask is used: forcing it to zero changes the descriptor
    with torch.no_grad():
        model.query.head.to_mask.bias.fill_(-1e4)
    assert not torch.allclose(desc, model.query(torch.randn(1, 3, 64, 64) * 0 + 1))


def test_without_msae_the_head_is_plain():
    model = CrossViewModel(CrossViewModelConfig(**{**SMALL, "msae": False}))
    assert not hasattr(model.query.head, "scales")
    assert model.query(torch.randn(1, 3, 64, 64)).shape == (1, 32)


def test_full_width_trunk_matches_vgg16_and_loads_a_local_state_dict(tmp_path):
    reference = vgg16(weights=None)
    path = tmp_path / "vgg16-local.pth"
    torch.save(reference.state_dict(), path)
    trunk = VGG16Trunk(width=1.0, pretrained=True, weights_path=str(path))
    assert trunk.channels == [256, 512, 512]
    for i, layer in enumerate(trunk.features):
        if isinstance(layer, torch.nn.Conv2d):
            assert torch.equal(layer.weight, reference.features[i].weight)
    x = torch.randn(1, 3, 64, 64)
    assert torch.allclose(trunk(x)[-1], reference.features[:30](x), atol=1e-5)


def test_missing_imagenet_weights_say_where_to_put_them(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    with pytest.raises(MissingWeightsError, match=vgg_module.IMAGENET_FILE) as err:
        VGG16Trunk(width=1.0, pretrained=True)
    assert str(tmp_path / "hub" / "checkpoints") in str(err.value)
    with pytest.raises(MissingWeightsError, match="does not exist"):
        VGG16Trunk(width=1.0, pretrained=True, weights_path=str(tmp_path / "nope.pth"))


def test_hub_cache_is_used_when_present(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    (tmp_path / "checkpoints").mkdir()
    torch.save(vgg16(weights=None).state_dict(), tmp_path / "checkpoints" / vgg_module.IMAGENET_FILE)
    VGG16Trunk(width=1.0, pretrained=True)


def test_pretrained_needs_full_width():
    with pytest.raises(ValueError, match="width=1.0"):
        VGG16Trunk(width=0.5, pretrained=True)


def test_batchnorm_trunk_taps_the_same_layers():
    plain, bn = VGG16Trunk(width=0.125), VGG16Trunk(width=0.125, batchnorm=True)
    assert plain.channels == bn.channels == [32, 64, 64]
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in bn.features)
    x = torch.randn(2, 3, 64, 64)
    assert [t.shape for t in plain(x)] == [t.shape for t in bn(x)] == [
        (2, 32, 16, 16), (2, 64, 8, 8), (2, 64, 4, 4)]
