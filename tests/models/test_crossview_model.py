"""The two-branch VGG16 + MSAE network: shapes, independence of the branches, ablation head, weight loading."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from geoloc.models import vgg as vgg_module
from geoloc.models.msae import MSAEHead, PlainHead
from geoloc.models.vgg import MissingWeightsError, VGG16Trunk
from torchvision.models import vgg16

from conftest import small_model


def test_descriptors_are_l2_normalised_and_shaped():
    model = small_model()
    q, r = model(torch.randn(2, 3, 64, 64), torch.randn(2, 3, 64, 64))
    assert q.shape == r.shape == (2, 32)
    assert torch.allclose(q.norm(dim=1), torch.ones(2), atol=1e-5)
    # a panorama-shaped query (alignment none/polar) also works
    assert model.query(torch.randn(1, 3, 32, 160)).shape == (1, 32)


def test_branches_share_no_weights():
    model = small_model()
    q_ids = {id(p) for p in model.query.parameters()}
    assert not q_ids & {id(p) for p in model.reference.parameters()}


def forced_mask(head, value: float):
    """Hook that replaces the mask logits, so sigmoid gives exactly 1 (value=+1e4) or 0 (value=-1e4)."""
    return head.to_mask.register_forward_hook(lambda module, args, out: torch.full_like(out, value))


def msae_by_hand(head, taps, activation=F.relu):
    """MSAE head written out step by step from the paper's description, with the head's own weights; eq. 3's
    branches end in `activation` (the identity: eq. 3 as written)."""
    size = taps[-1].shape[-2:]
    x = torch.cat([F.adaptive_avg_pool2d(t, size) for t in taps], dim=1)
    multi = torch.cat([activation(F.conv2d(x, c.weight, c.bias, padding=c.kernel_size[0] // 2)) for c in head.scales],
                      dim=1)
    assert [c.kernel_size[0] for c in head.scales] == [3, 5, 7]  # eq. 3: three receptive fields
    mask = torch.sigmoid(F.conv2d(multi, head.to_mask.weight, head.to_mask.bias))
    d = head.descriptor
    pooled = F.adaptive_avg_pool2d(F.relu(F.conv2d(x * mask, d.proj.weight, d.proj.bias)), d.pool)
    return F.normalize(F.linear(pooled.flatten(1), d.fc.weight, d.fc.bias), dim=1), mask


def test_msae_head_matches_a_step_by_step_formulation():
    torch.manual_seed(0)
    head = MSAEHead([4, 6, 6], dim=16, scale_channels=5, proj_channels=3, pool=2)
    taps = [torch.randn(2, 4, 16, 16), torch.randn(2, 6, 8, 8), torch.randn(2, 6, 4, 4)]
    assert [c.kernel_size for c in (head.to_mask, head.descriptor.proj)] == [(1, 1), (1, 1)]  # 1x1 convolutions
    desc, mask = head(taps, return_attention=True)
    torch.testing.assert_close(head(taps), desc)  # the descriptor alone by default
    expected_desc, expected_mask = msae_by_hand(head, taps)
    torch.testing.assert_close(mask, expected_mask)
    torch.testing.assert_close(desc, expected_desc)
    # the mask is learned: gradients reach the attention convolutions, as they do by hand
    weights = torch.randn_like(desc)
    names, params = zip(*head.named_parameters())
    got = dict(zip(names, torch.autograd.grad((desc * weights).sum(), params)))
    expected = dict(zip(names, torch.autograd.grad((expected_desc * weights).sum(), params)))
    for name in names:
        torch.testing.assert_close(got[name], expected[name], msg=name)
    assert got["to_mask.weight"].abs().sum() > 0 and got["scales.2.weight"].abs().sum() > 0


def test_attention_mask_reweights_the_features():
    model = small_model().eval()
    x, other = torch.randn(1, 3, 64, 64), torch.randn(1, 3, 64, 64)
    desc, mask = model.query(x, return_attention=True)
    assert mask.shape == (1, 1, 4, 4) and (mask > 0).all() and (mask < 1).all() and mask.std() > 0
    head = model.query.head
    taps = model.query.trunk(x)
    unweighted = head.descriptor(torch.cat([F.adaptive_avg_pool2d(t, (4, 4)) for t in taps], dim=1))
    # the same input with the mask forced to one gives the descriptor of the unweighted features ...
    handle = forced_mask(head, 1e4)
    torch.testing.assert_close(model.query(x), unweighted)
    handle.remove()
    # ... which the real mask changes
    assert (desc - unweighted).abs().max() > 1e-3
    # with the mask forced to zero nothing of the image gets through: two inputs, one descriptor
    handle = forced_mask(head, -1e4)
    torch.testing.assert_close(model.query(x), model.query(other))
    handle.remove()
    torch.testing.assert_close(model.query(x), desc)  # the hooks are gone


@pytest.mark.parametrize("head", [MSAEHead, PlainHead])
def test_head_defaults_are_the_configs(head, tmp_path):
    """The modules' sizes are the paper head's as composed (head=msae, head=fc); the branches' ReLU is the module's
    default (geoloc's choice, which checkpoints without the key were trained with), which the CPU head keeps and
    the paper's head drops (eq. 3)."""
    from conftest import compose_train

    name = "msae" if head is MSAEHead else "fc"
    built = head([4, 4, 4], dim=8)
    cfg = compose_train([f"head={name}", f"run_dir={tmp_path}"]).head
    assert built.descriptor.proj.out_channels == cfg.proj_channels and built.descriptor.pool == cfg.pool
    if head is MSAEHead:
        assert built.scales[0].out_channels == cfg.scale_channels
        assert built.scale_activation == "relu" and cfg.scale_activation == "none"
        assert compose_train([f"run_dir={tmp_path}"]).head.scale_activation == "relu"  # the CPU default: msae_cpu


def test_eq3_as_written_drops_the_branch_activation():
    """With the same weights, "none" is eq. 3 (s = U_p k_p(d) + c, no activation) and "relu" is not: the masks
    differ, each as written out by hand."""
    torch.manual_seed(0)
    relu = MSAEHead([4, 6, 6], dim=16, scale_channels=5, proj_channels=3, pool=2)
    plain = MSAEHead([4, 6, 6], dim=16, scale_channels=5, proj_channels=3, pool=2, scale_activation="none")
    plain.load_state_dict(relu.state_dict())  # the option adds no weights
    taps = [torch.randn(2, 4, 16, 16), torch.randn(2, 6, 8, 8), torch.randn(2, 6, 4, 4)]
    (d_relu, m_relu), (d_plain, m_plain) = relu(taps, return_attention=True), plain(taps, return_attention=True)
    assert (m_relu - m_plain).abs().max() > 1e-3
    expected_desc, expected_mask = msae_by_hand(plain, taps, activation=lambda x: x)
    torch.testing.assert_close(m_plain, expected_mask)
    torch.testing.assert_close(d_plain, expected_desc)
    relu_desc, relu_mask = msae_by_hand(relu, taps, activation=torch.relu)
    torch.testing.assert_close((d_relu, m_relu), (relu_desc, relu_mask))
    with pytest.raises(ValueError, match=r"scale_activation must be one of \('relu', 'none'\)"):
        MSAEHead([4], dim=8, scale_activation="gelu")


@pytest.mark.parametrize("head", [
    {"name": "msae", "scale_channels": 4, "proj_channels": 3, "pool": 2},
    {"name": "msae", "scale_channels": 4, "proj_channels": 3, "pool": 2, "scale_activation": "none"},
    {"name": "fc", "proj_channels": 3, "pool": 2},
    {"name": "gap"},
    {"name": "mean_max", "module": "tests/plugins/mean_max.py"},
])
@pytest.mark.slow
def test_branch_features_give_the_same_descriptor_with_its_maps(head):
    """features(x) is forward(x) bit for bit, with the backbone's maps and the head's map before pooling."""
    from conftest import REPO
    from geoloc.models.crossview import CrossViewModel, CrossViewModelConfig

    if "module" in head:
        head = {**head, "module": str(REPO / head["module"])}
    torch.manual_seed(0)
    backbone = {"name": "vgg16", "width": 0.0625, "pretrained": False, "batchnorm": False}
    model = CrossViewModel(backbone, head, CrossViewModelConfig(dim=8)).eval()
    query, reference = torch.randn(2, 3, 32, 32), torch.randn(2, 3, 32, 32)
    q, r = model.features(query, reference)
    expected = model(query, reference)
    assert torch.equal(q.descriptor, expected[0]) and torch.equal(r.descriptor, expected[1])
    maps = model.query.trunk(query)
    assert len(q.maps) == len(maps) and all(torch.equal(a, b) for a, b in zip(q.maps, maps))
    if head["name"] == "mean_max":  # a head without features(): the descriptor and the maps, no head map
        assert q.head_map is None and q.attention is None
        return
    h, w = maps[-1].shape[-2:]
    channels = {"msae": 3, "fc": 3, "gap": maps[-1].shape[1]}[head["name"]]
    assert q.head_map.shape == (2, channels, h, w)
    if head["name"] == "msae":
        assert torch.equal(q.attention, model.query(query, return_attention=True)[1])
    else:
        assert q.attention is None


def test_plain_head_codes_conv5_3_alone():
    torch.manual_seed(0)
    head = PlainHead([4, 6, 8], dim=16, proj_channels=3, pool=2)
    taps = [torch.randn(2, 4, 16, 16), torch.randn(2, 6, 8, 8), torch.randn(2, 8, 4, 4)]
    d = head.descriptor
    assert d.proj.kernel_size == (1, 1)
    pooled = F.adaptive_avg_pool2d(F.relu(F.conv2d(taps[-1], d.proj.weight, d.proj.bias)), 2)
    expected = F.normalize(F.linear(pooled.flatten(1), d.fc.weight, d.fc.bias), dim=1)
    torch.testing.assert_close(head(taps), expected)
    desc, mask = head(taps, return_attention=True)  # figures draw a uniform mask for the ablation
    torch.testing.assert_close(desc, expected)
    assert torch.equal(mask, torch.ones(2, 1, 4, 4))


def test_without_msae_the_head_is_plain():
    model = small_model(msae=False)
    assert not hasattr(model.query.head, "scales")
    assert model.query(torch.randn(1, 3, 64, 64)).shape == (1, 32)


@pytest.mark.slow
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


def _vgg16_file(tmp_path, keep=None, reshape=None, name="vgg16-part.pth"):
    """torchvision's VGG16 state dict, with only the keys `keep` accepts, and `reshape` keys cut in half."""
    state = vgg16(weights=None).state_dict()
    state = {k: (v[: v.shape[0] // 2] if reshape and reshape(k) else v) for k, v in state.items()
             if keep is None or keep(k)}
    torch.save(state, tmp_path / name)
    return str(tmp_path / name)


def test_a_partial_vgg16_file_is_refused_naming_what_it_lacks(tmp_path):
    # the first 10 convolutions (features.0 .. features.21) only: conv5_x is missing
    path = _vgg16_file(tmp_path, keep=lambda k: k.startswith("features.") and int(k.split(".")[1]) < 22)
    with pytest.raises(ValueError, match=r"holds 20 of the 26 tensors of the VGG16 trunk.*missing features\.24\.weight"
                       r".*backbone\.weights_path") as err:
        VGG16Trunk(width=1.0, pretrained=True, weights_path=path)
    assert path in str(err.value)


def test_a_vgg16_file_of_other_shapes_is_refused(tmp_path):
    path = _vgg16_file(tmp_path, reshape=lambda k: k == "features.28.weight")
    with pytest.raises(ValueError, match=r"mis-shaped features\.28\.weight: file \(256, 512, 3, 3\) vs VGG16 "
                       r"\(512, 512, 3, 3\)"):
        VGG16Trunk(width=1.0, pretrained=True, weights_path=path)


def test_a_vgg16_file_cut_short_is_refused_as_unreadable(tmp_path):
    path = tmp_path / "vgg16-cut.pth"
    torch.save(vgg16(weights=None).features[:5].state_dict(), path)
    path.write_bytes(path.read_bytes()[:4000])  # a copy that stopped part way
    with pytest.raises(ValueError, match=f"cannot read {path} as a state dict"):
        VGG16Trunk(width=1.0, pretrained=True, weights_path=str(path))


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
