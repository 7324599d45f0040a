"""tools/export_trunk.py: a checkpoint's shared trunk written as shippable weights loads back into the trunk it
came from through backbone.weights_path; an unshared model needs --branch; nothing existing is overwritten."""

import hashlib
import importlib.util
import json
from pathlib import Path

import pytest
import torch
import yaml
from conftest import REPO

from geoloc.models.backbones import vgg16
from geoloc.models.vgg import VGG16Trunk

spec = importlib.util.spec_from_file_location("export_trunk", REPO / "tools" / "export_trunk.py")
export_trunk = importlib.util.module_from_spec(spec)
spec.loader.exec_module(export_trunk)


def fake_checkpoint(path: Path, shared: bool) -> VGG16Trunk:
    """A geoloc checkpoint dict holding two trunks (the same one twice where shared), as the trainer writes it."""
    torch.manual_seed(0)
    query, reference = VGG16Trunk(width=0.125, batchnorm=True), VGG16Trunk(width=0.125, batchnorm=True)
    task = {f"model.query.trunk.{k}": v for k, v in query.state_dict().items()}
    task.update({f"model.reference.trunk.{k}": v for k, v in (query if shared else reference).state_dict().items()})
    config = {"seed": 3, "backbone": {"name": "vgg16", "width": 0.125, "pretrained": False, "batchnorm": True},
              "dataset": {"name": "synthetic", "preset": "small", "train_size": 20, "val_size": 5, "seed": 0,
                          "batch_size": 4}, "model": {"dim": 8, "shared": shared}}
    torch.save({"task": task, "config": yaml.safe_dump(config), "epoch": 2, "global_step": 15}, path)
    return query


def test_a_shared_trunk_is_written_with_its_card_and_loads_back(tmp_path):
    source = fake_checkpoint(tmp_path / "last.pt", shared=True)
    export_trunk.main([str(tmp_path / "last.pt"), str(tmp_path / "w"), "mine", "--recipe", "python train.py x"])
    card = json.loads((tmp_path / "w" / "mine.json").read_text())
    data = (tmp_path / "w" / "mine.pt").read_bytes()
    assert card["sha256"] == hashlib.sha256(data).hexdigest()
    assert (card["backbone"], card["seed"], card["epochs"], card["pairs"], card["shared_trunk"]) == (
        {"name": "vgg16", "width": 0.125, "batchnorm": True}, 3, 3, 60, True)
    loaded = vgg16(width=0.125, pretrained=True, weights_path=str(tmp_path / "w" / "mine.pt"), batchnorm=True)
    assert all(torch.equal(loaded.state_dict()[k], v) for k, v in source.state_dict().items())
    with pytest.raises(SystemExit, match="nothing is overwritten"):
        export_trunk.main([str(tmp_path / "last.pt"), str(tmp_path / "w"), "mine", "--recipe", "again"])


def test_an_unshared_model_needs_the_branch_named(tmp_path):
    fake_checkpoint(tmp_path / "last.pt", shared=False)
    with pytest.raises(SystemExit, match="--branch"):
        export_trunk.main([str(tmp_path / "last.pt"), str(tmp_path / "w"), "mine", "--recipe", "r"])
    export_trunk.main([str(tmp_path / "last.pt"), str(tmp_path / "w"), "mine", "--recipe", "r", "--branch", "query"])
    assert (tmp_path / "w" / "mine.pt").is_file()
