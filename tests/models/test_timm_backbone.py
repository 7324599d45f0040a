"""timm backbones: maps fine to coarse for ConvNeXt and ViT, the MSAE head on them, offline-only weight loading."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest
import safetensors.torch
import timm
import torch
from geoloc.models.msae import MSAEHead
from geoloc.models.timm_backbone import default_out_indices, timm_backbone
from geoloc.models.vgg import MissingWeightsError

from conftest import REPO

CONVNEXT = dict(dims=[16, 32, 64, 128], depths=[1, 1, 2, 1])  # a CPU-sized ConvNeXt
DEIT = dict(embed_dim=48, depth=6, num_heads=3)  # a CPU-sized DeiT (patch 16)


@pytest.fixture
def network_attempts(monkeypatch):
    """Every socket connection or name lookup fails and is recorded: the tests assert there were none."""
    attempts = []

    def refuse(*args, **kwargs):
        attempts.append(args)
        raise OSError("this test has no network")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    return attempts


@pytest.fixture
def empty_caches(tmp_path, monkeypatch):
    """The Hugging Face and torch hub caches point at empty folders under tmp_path."""
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf"))
    monkeypatch.delenv("HUGGINGFACE_HUB_CACHE", raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    return tmp_path


def test_convnext_gives_the_last_three_stages_fine_to_coarse():
    backbone = timm_backbone("convnext_tiny", model_args=CONVNEXT)
    maps = backbone(torch.randn(2, 3, 64, 96))
    assert backbone.out_indices == [1, 2, 3]
    assert backbone.channels == [32, 64, 128] == [m.shape[1] for m in maps]
    assert [tuple(m.shape[-2:]) for m in maps] == [(8, 12), (4, 6), (2, 3)]  # strides 8, 16, 32, non-square kept
    assert backbone.reductions == [8, 16, 32]


def vit_maps_by_hand(vit, x, blocks):
    """Patch tokens after the given blocks, class token dropped, row-major tokens laid out as B×C×h×w."""
    tokens = vit.norm_pre(vit.patch_drop(vit._pos_embed(vit.patch_embed(x))))
    h, w = vit.patch_embed.grid_size
    maps = []
    for i, block in enumerate(vit.blocks):
        tokens = block(tokens)
        if i in blocks:
            patches = tokens[:, vit.num_prefix_tokens:]
            maps.append(patches.reshape(x.shape[0], h, w, -1).permute(0, 3, 1, 2))
    return maps


def test_deit_gives_three_evenly_spaced_blocks_on_the_patch_grid():
    torch.manual_seed(0)
    backbone = timm_backbone("deit_tiny_patch16_224", model_args=dict(img_size=[32, 64], **DEIT)).eval()
    x = torch.randn(2, 3, 32, 64)
    maps = backbone(x)
    assert backbone.out_indices == [1, 3, 5]  # the ends of the three thirds of 6 blocks
    assert backbone.channels == [48, 48, 48] == [m.shape[1] for m in maps]
    assert [tuple(m.shape) for m in maps] == [(2, 48, 2, 4)] * 3  # the 2x4 patch grid, not 4x2
    expected = vit_maps_by_hand(backbone.body.model, x, [1, 3, 5])
    assert not torch.allclose(expected[0], expected[1])  # the blocks differ, so the order is checked too
    for got, want in zip(maps, expected):
        torch.testing.assert_close(got, want)


def test_default_out_indices():
    assert default_out_indices([4, 8, 16, 32]) == [1, 2, 3]  # ConvNeXt stages
    assert default_out_indices([2, 4, 8, 16, 32]) == [2, 3, 4]  # ResNet-like, with a stem level
    assert default_out_indices([16] * 12) == [3, 7, 11]  # ViT-B: blocks 4, 8, 12 (1-based)
    assert default_out_indices([16] * 2) == [0, 1]
    assert default_out_indices([16]) == [0]


def test_out_indices_pick_levels_fine_to_coarse():
    backbone = timm_backbone("convnext_tiny", out_indices=[3, -3], model_args=CONVNEXT)
    assert backbone.out_indices == [1, 3]
    assert [m.shape[-1] for m in backbone(torch.randn(1, 3, 64, 64))] == [8, 2]


@pytest.mark.parametrize("model, model_args", [("convnext_tiny", CONVNEXT),
                                               ("deit_tiny_patch16_224", dict(img_size=64, **DEIT))])
def test_msae_head_runs_on_the_maps(model, model_args):
    backbone = timm_backbone(model, model_args=model_args)
    head = MSAEHead(in_channels=backbone.channels, dim=32)
    desc = head(backbone(torch.randn(3, 3, 64, 64)))
    assert desc.shape == (3, 32)
    torch.testing.assert_close(desc.norm(dim=1), torch.ones(3))
    assert not torch.allclose(desc[0], desc[1])  # not collapsed


def saved_convnext(path, seed=0, **args):
    """A full timm ConvNeXt with seeded random weights, its state dict written to `path`."""
    torch.manual_seed(seed)
    full = timm.create_model("convnext_tiny", **{**CONVNEXT, **args}).eval()
    if str(path).endswith(".safetensors"):
        safetensors.torch.save_file(full.state_dict(), path)
    else:
        torch.save(full.state_dict(), path)
    return full


def convnext_from(path):
    return timm_backbone("convnext_tiny", pretrained=True, weights_path=str(path), model_args=CONVNEXT)


@pytest.mark.parametrize("name", ["weights.pth", "weights.safetensors"])
def test_weights_path_loads_the_saved_weights(tmp_path, name, network_attempts, empty_caches):
    full = saved_convnext(tmp_path / name)
    backbone = convnext_from(tmp_path / name).eval()
    x = torch.randn(2, 3, 64, 64)
    expected = full.forward_intermediates(x, indices=[1, 2, 3], intermediates_only=True)
    for got, want in zip(backbone(x), expected):
        assert torch.equal(got, want)
    random_init = timm_backbone("convnext_tiny", model_args=CONVNEXT).eval()
    assert not torch.allclose(random_init(x)[-1], expected[-1])  # the equality above is not by chance
    assert network_attempts == []


def test_vit_weights_load_at_another_img_size(tmp_path, network_attempts):
    """timm's own checkpoint filter resamples the position embeddings; every other tensor is copied."""
    torch.manual_seed(0)
    source = timm.create_model("deit_tiny_patch16_224", img_size=64, **DEIT)
    with torch.no_grad():  # one vector at every patch position: any resampling of the 4x4 grid must keep it
        source.pos_embed[:, 1:] = torch.randn(48)
    torch.save({"state_dict": source.state_dict()}, tmp_path / "deit.pth")  # a training checkpoint's wrapping
    backbone = timm_backbone("deit_tiny_patch16_224", pretrained=True, weights_path=str(tmp_path / "deit.pth"),
                             model_args=dict(img_size=32, **DEIT))
    vit = backbone.body.model
    assert torch.equal(vit.blocks[5].mlp.fc2.weight, source.blocks[5].mlp.fc2.weight)
    assert torch.equal(vit.cls_token, source.cls_token)
    assert vit.pos_embed.shape == (1, 1 + 2 * 2, 48)  # class token + the 2x2 grid of a 32x32 input
    torch.testing.assert_close(vit.pos_embed[:, :1], source.pos_embed[:, :1])
    torch.testing.assert_close(vit.pos_embed[:, 1:], source.pos_embed[:, 1:5])
    assert network_attempts == []


def test_a_file_of_another_depth_names_the_keys(tmp_path):
    saved_convnext(tmp_path / "deeper.pth", depths=[1, 1, 3, 1])
    with pytest.raises(ValueError, match=r"does not fit timm model 'convnext_tiny'.*unexpected keys "
                                         r"\['stages\.2\.blocks\.2\."):
        convnext_from(tmp_path / "deeper.pth")
    saved_convnext(tmp_path / "shallower.pth", depths=[1, 1, 1, 1])
    with pytest.raises(ValueError, match=r"9 missing keys .*'stages\.2\.blocks\.1\.conv_dw\.bias'"):
        convnext_from(tmp_path / "shallower.pth")


def test_a_file_of_another_model_is_refused(tmp_path):
    torch.save(timm.create_model("resnet10t").state_dict(), tmp_path / "resnet.pth")
    with pytest.raises(ValueError, match=r"missing keys \['head\.norm\.bias'.*unexpected keys \['bn1\."):
        convnext_from(tmp_path / "resnet.pth")


def test_a_file_of_other_widths_is_refused(tmp_path):
    saved_convnext(tmp_path / "wider.pth", dims=[16, 32, 64, 256])
    with pytest.raises(ValueError, match=r"other tensor sizes .*size mismatch for stages\.3.*drop the "
                                         r"backbone\.model_args"):
        convnext_from(tmp_path / "wider.pth")


def test_a_file_that_is_no_state_dict_is_refused(tmp_path):
    (tmp_path / "notes.pth").write_text("not a checkpoint")
    with pytest.raises(ValueError, match=r"cannot read .*notes\.pth as a state dict"):
        convnext_from(tmp_path / "notes.pth")


def test_a_missing_weights_path_is_named(tmp_path):
    with pytest.raises(MissingWeightsError, match=r"backbone\.weights_path=.*nowhere\.pth' does not exist"):
        timm_backbone("convnext_tiny", pretrained=True, weights_path=str(tmp_path / "nowhere.pth"))


@pytest.mark.parametrize("model", ["convnext_tiny", "deit_tiny_patch16_224"])
def test_no_file_anywhere_says_where_it_looked_without_downloading(model, empty_caches, network_attempts):
    hub_id = timm.models.get_pretrained_cfg(model).hf_hub_id
    with pytest.raises(MissingWeightsError) as err:
        timm_backbone(model, pretrained=True)
    message = str(err.value)
    assert str(empty_caches / "hf") in message and hub_id in message and "model.safetensors" in message
    assert "backbone.weights_path=" in message and "backbone.pretrained=false" in message
    if model.startswith("deit"):  # timm's older URL weights: the torch hub cache is searched too
        assert str(empty_caches / "torch" / "hub" / "checkpoints" / "deit_tiny_patch16_224-a1311bcf.pth") in message
    assert network_attempts == []


def test_weights_are_found_in_the_hugging_face_cache(empty_caches, network_attempts):
    hub_id = timm.models.get_pretrained_cfg("convnext_tiny").hf_hub_id  # timm/convnext_tiny.in12k_ft_in1k
    repo = empty_caches / "hf" / f"models--{hub_id.replace('/', '--')}"
    (repo / "snapshots" / "c0ffee").mkdir(parents=True)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("c0ffee")
    full = saved_convnext(repo / "snapshots" / "c0ffee" / "model.safetensors", seed=3)
    backbone = timm_backbone("convnext_tiny", pretrained=True, model_args=CONVNEXT)
    assert torch.equal(backbone.body.stages_3.blocks[0].conv_dw.weight, full.stages[3].blocks[0].conv_dw.weight)
    assert network_attempts == []


def test_weights_are_found_in_the_torch_hub_cache(empty_caches, network_attempts):
    folder = empty_caches / "torch" / "hub" / "checkpoints"
    folder.mkdir(parents=True)
    torch.manual_seed(1)
    source = timm.create_model("deit_tiny_patch16_224", img_size=32, **DEIT)
    torch.save(source.state_dict(), folder / "deit_tiny_patch16_224-a1311bcf.pth")
    backbone = timm_backbone("deit_tiny_patch16_224", pretrained=True, model_args=dict(img_size=32, **DEIT))
    assert torch.equal(backbone.body.model.patch_embed.proj.weight, source.patch_embed.proj.weight)
    assert network_attempts == []


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match=r"backbone\.model='convnxt_tiny' is not a timm model.*'convnext_tiny'"):
        timm_backbone("convnxt_tiny")
    with pytest.raises(ValueError, match=r"backbone\.model='hf-hub:timm/convnext_tiny' is not a timm model"):
        timm_backbone("hf-hub:timm/convnext_tiny")  # timm would download this one's config
    with pytest.raises(ValueError, match=r"backbone\.model_args=\{'widths': \[8\]\} do not fit .*'widths'"):
        timm_backbone("convnext_tiny", model_args={"widths": [8]})
    with pytest.raises(ValueError, match=r"backbone\.out_indices=\[4\] .* 4 feature levels"):
        timm_backbone("convnext_tiny", out_indices=[4], model_args=CONVNEXT)
    with pytest.raises(ValueError, match=r"backbone\.pretrained=false"):
        timm_backbone("convnext_tiny", weights_path="weights.pth", model_args=CONVNEXT)


def test_a_vit_input_of_another_size_names_img_size():
    backbone = timm_backbone("deit_tiny_patch16_224", model_args=dict(img_size=32, **DEIT))
    with pytest.raises(ValueError, match=r"backbone\.model_args\.img_size=\[64, 32\]"):
        backbone(torch.randn(1, 3, 64, 32))


@pytest.mark.slow
def test_registered_and_timm_imported_only_when_built():
    import geoloc.models.timm_backbone as module
    from geoloc import registry

    assert registry._registry["backbone"]["timm"] is module.timm_backbone
    code = "import sys, geoloc, geoloc.models, geoloc.models.timm_backbone; print('timm' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
