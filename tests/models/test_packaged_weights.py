"""Weights shipped inside the package (`backbone.weights_path=geoloc:NAME`): the shipped file matches its card and
loads into the trunk it was trained as; unknown names, damaged files and other trunks are refused; and a trunk
state dict saved by the test loads through the same path from a plain file."""

import json
import shutil

import pytest
import torch

from conftest import REPO

from geoloc.models import packaged_weights
from geoloc.models.backbones import vgg16
from geoloc.models.vgg import VGG16Trunk

NAME = "geoloc:synthetic_vgg16_cpu"


def test_the_shipped_trunk_matches_its_card_and_loads_exactly():
    card = packaged_weights.card(NAME)
    assert card["backbone"] == {"name": "vgg16", "width": 0.125, "batchnorm": True}
    assert {"recipe", "seed", "data", "sha256", "epochs"} <= set(card)
    stored = torch.load(packaged_weights.packaged_file(NAME, "vgg16"), map_location="cpu", weights_only=True)
    trunk = vgg16(width=0.125, pretrained=True, weights_path=NAME, batchnorm=True)
    own = trunk.state_dict()
    assert set(own) == set(stored)
    assert all(torch.equal(own[k], stored[k]) for k in own)
    fresh = vgg16(width=0.125, pretrained=False, batchnorm=True).state_dict()
    assert not torch.equal(fresh["features.0.weight"], own["features.0.weight"])


def test_one_forward_pass_matches_the_stored_output():
    """The output stored when the weights were shipped (tests/fixtures/synthetic_vgg16_cpu_forward.json): a changed
    file, a load into the wrong layers or a changed trunk definition moves it."""
    stored = json.loads((REPO / "tests/fixtures/synthetic_vgg16_cpu_forward.json").read_text())
    assert stored["sha256"] == packaged_weights.card(NAME)["sha256"]
    trunk = vgg16(width=0.125, pretrained=True, weights_path=NAME, batchnorm=True).eval()
    x = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        taps = trunk(x)
    assert [list(t.shape) for t in taps] == stored["tap_shapes"]
    assert [float(t.double().sum()) for t in taps] == pytest.approx(stored["tap_sums"], rel=1e-4)
    assert torch.allclose(taps[-1].flatten(), torch.tensor(stored["conv5_3"]), atol=1e-4)


def test_an_unknown_name_lists_the_shipped_ones():
    with pytest.raises(packaged_weights.PackagedWeightsError, match="synthetic_vgg16_cpu"):
        vgg16(width=0.125, pretrained=True, weights_path="geoloc:imagenet_vgg16_cpu", batchnorm=True)


def test_another_trunk_is_told_which_settings_fit():
    with pytest.raises(ValueError, match="backbone.width=0.125"):
        vgg16(width=0.25, pretrained=True, weights_path=NAME, batchnorm=True)
    with pytest.raises(ValueError, match="batchnorm=true"):
        vgg16(width=0.125, pretrained=True, weights_path=NAME, batchnorm=False)
    with pytest.raises(ValueError, match="vgg16 trunk, not a timm one"):
        packaged_weights.packaged_file(NAME, "timm")


def test_a_damaged_file_is_refused_by_its_checksum(tmp_path, monkeypatch):
    for name in ("synthetic_vgg16_cpu.json", "synthetic_vgg16_cpu.pt"):
        shutil.copy(packaged_weights.FOLDER / name, tmp_path / name)
    monkeypatch.setattr(packaged_weights, "FOLDER", tmp_path)
    data = bytearray((tmp_path / "synthetic_vgg16_cpu.pt").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (tmp_path / "synthetic_vgg16_cpu.pt").write_bytes(bytes(data))
    with pytest.raises(ValueError, match="sha256"):
        vgg16(width=0.125, pretrained=True, weights_path=NAME, batchnorm=True)
    (tmp_path / "synthetic_vgg16_cpu.pt").unlink()
    with pytest.raises(packaged_weights.PackagedWeightsError, match="Reinstall"):
        vgg16(width=0.125, pretrained=True, weights_path=NAME, batchnorm=True)


def test_a_narrow_trunk_saved_by_the_user_loads_from_its_file(tmp_path):
    source = VGG16Trunk(width=0.125, batchnorm=True)
    torch.save({f"features.{k}": v for k, v in source.features.state_dict().items()}, tmp_path / "trunk.pt")
    loaded = vgg16(width=0.125, pretrained=True, weights_path=str(tmp_path / "trunk.pt"), batchnorm=True)
    assert all(torch.equal(loaded.state_dict()[k], v) for k, v in source.state_dict().items())
    with pytest.raises(ValueError, match="width=1.0"):  # no file: ImageNet's full-width weights are all there is
        vgg16(width=0.125, pretrained=True, batchnorm=True)


def test_every_card_names_a_shipped_file():
    for name in packaged_weights.names():
        card = json.loads((packaged_weights.FOLDER / f"{name}.json").read_text())
        assert card["name"] == name and (packaged_weights.FOLDER / card["file"]).is_file()
