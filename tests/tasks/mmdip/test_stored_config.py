"""Checkpoints store their config in the layout of their day; geoloc.tasks.mmdip.stored_config upgrades format 1
(segmenter keys flat in task.segmentation, task.translation.loss_weights, synthetic-layout keys in every dataset
section) to format 2, so a format-1 checkpoint of either phase still evaluates."""

from __future__ import annotations

import json

import pytest
import torch
from geoloc.config import to_yaml
from geoloc.engine import checkpoint
from geoloc.launch import run
from geoloc.tasks.mmdip.joint import JointTask
from geoloc.tasks.mmdip.pipeline import parse
from geoloc.tasks.mmdip.segmentation import SegmentationTask
from geoloc.tasks.mmdip.stored_config import format_1_to_2, is_format_1
from omegaconf import OmegaConf

from conftest import compose_evaluate, compose_train
from helpers.dynamic_data import TINY_MMDIP, write_tiny_dynamic

SYNTHETIC = {"preset": "dynamic_small", "train_size": 200, "val_size": 100, "view_size": 128, "seed": 0, "workers": 2}


def test_format_1_becomes_format_2():
    old = {"seed": 0,
           "task": {"name": "mmdip", "segmentation": {"model": "unet", "epochs": 6, "unet_num_downs": 3, "unet_ngf": 4,
                                                      "fcn_width": 16},
                    "translation": {"variant": "ssggnet", "loss_weights": "paper", "num_downs": 5},
                    "vpr": {"levels": 2}},
           "dataset": {"name": "carla4", "root": "/data", "image_size": [64, 64], **SYNTHETIC}}
    assert is_format_1(old)
    new = format_1_to_2(old)
    assert new == {"seed": 0,
                   "task": {"name": "mmdip", "segmentation": {"model": "unet", "epochs": 6, "unet": {"num_downs": 3,
                                                                                                     "ngf": 4},
                                                              "fcn": {"width": 16}},
                            "translation": {"variant": "ssggnet", "generator_loss": {"name": "paper"}, "num_downs": 5},
                            "vpr": {"levels": 2}},
                   "dataset": {"name": "carla4", "root": "/data", "image_size": [64, 64]}}  # keys only dynamic read
    assert not is_format_1(new)
    dynamic = {**old, "dataset": {"name": "dynamic", "root": None, **SYNTHETIC}}
    assert format_1_to_2(dynamic)["dataset"] == dynamic["dataset"]  # the synthetic reader's own keys now


def format_1(cfg) -> str:
    """The config text the trainer stored in format 1 for the run `cfg` (format 2) describes."""
    old = OmegaConf.to_container(cfg, resolve=True)
    segmentation, translation = old["task"]["segmentation"], old["task"]["translation"]
    unet, fcn = segmentation.pop("unet", {}), segmentation.pop("fcn", {})
    segmentation.update(unet_num_downs=unet.get("num_downs", 5), unet_ngf=unet.get("ngf", 32),
                        fcn_width=fcn.get("width", 32))
    translation["loss_weights"] = translation.pop("generator_loss")["name"]
    old["dataset"].update(SYNTHETIC)
    return OmegaConf.to_yaml(OmegaConf.create(old))


@pytest.mark.parametrize("phase", ["phase1", "phase2"])
def test_a_format_1_checkpoint_evaluates_as_its_format_2_copy(phase, tmp_path, one_thread):
    """The same weights under both layouts give the same metrics; a U-Net of non-default size only loads when its
    size keys are carried over."""
    root = write_tiny_dynamic(tmp_path / "dyn", n_train=2, n_val=4)
    cfg = compose_train([*TINY_MMDIP, f"dataset.root={root}", "task.segmentation.model=unet",
                         "+task.segmentation.unet.num_downs=3", "+task.segmentation.unet.ngf=4",
                         "task.translation.generator_loss.name=paper", f"run_dir={tmp_path}"])
    task_cfg = parse(cfg)[0]
    torch.manual_seed(0)
    fractions = [1 / 8] * 8
    task = (JointTask(task_cfg, fractions, training=False) if phase == "phase2" else
            SegmentationTask(task_cfg.segmentation, task_cfg.num_classes, fractions))
    assert format_1(cfg) != to_yaml(cfg) and is_format_1(OmegaConf.to_container(OmegaConf.create(format_1(cfg))))
    scores = {}
    for layout, text in (("format_2", to_yaml(cfg)), ("format_1", format_1(cfg))):
        ckpt = tmp_path / layout / phase / "best.pt"
        checkpoint.save_atomic({"task": task.state_dict(), "config": text}, ckpt)
        out = tmp_path / f"{layout}.json"
        run.evaluate(compose_evaluate([f"ckpt={ckpt}", f"metrics_out={out}", "device=cpu", "progress=false"]))
        scores[layout] = {k: v for k, v in json.loads(out.read_text()).items() if not k.startswith("ms/")}  # timings
    assert scores["format_1"] == scores["format_2"]
    assert {"R@1", "SSIM"} <= set(scores["format_1"]) if phase == "phase2" else "MIoU" in scores["format_1"]
