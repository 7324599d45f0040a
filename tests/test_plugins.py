"""Components from outside the geoloc package (tests/plugins/: one .py and one yaml each) plug in from the command
line with no edit to geoloc: a dataset, a backbone, a head, a loss, an optimizer and a sampler.

The yaml files live in tests/plugins/conf/<group>/, found through `hydra.searchpath`; each names its module
(`module: plugins.tiny_cnn`), which the registry imports before looking the name up.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from geoloc import registry
from geoloc.config import ConfigError
from geoloc.tasks.crossview.datasets import read_split

from conftest import REPO, compose_train, write_cvusa
from helpers.crossview_runs import task_of

PLUGINS = Path(__file__).parent / "plugins"
SEARCHPATH = f"hydra.searchpath=[file://{PLUGINS / 'conf'}]"
ALL_PLUGINS = ["dataset=tiny_folder", "backbone=tiny_cnn", "head=mean_max", "loss=margin_triplet", "optim=sgd",
               "sampler=in_order"]


def tiny_folder(root: Path, n_train: int = 8, n_val: int = 6) -> Path:
    """The plug-in dataset's own layout, written from a tiny CVUSA tree."""
    cvusa = write_cvusa(root.parent / f"{root.name}_src", n_train, n_val)
    for split in ("train", "val"):
        for kind in ("street", "aerial"):
            (root / split / kind).mkdir(parents=True)
        rows = (cvusa / "splits" / f"{split}-19zl.csv").read_text().split()
        for row in rows:
            aerial, street = row.split(",")[:2]
            name = Path(street).stem + ".png"
            (root / split / "street" / name).write_bytes((cvusa / street).read_bytes())
            (root / split / "aerial" / name).write_bytes((cvusa / aerial).read_bytes())
    return root


QUIET = ["trainer.num_workers=0", "trainer.progress=false", "trainer.device=cpu", "figures=false", "model.dim=16"]


def plugin_cfg(root: Path, run_dir: Path, *extra):
    return compose_train([*QUIET, SEARCHPATH, *ALL_PLUGINS, f"dataset.root={root}", f"run_dir={run_dir}",
                          "dataset.aerial_size=32", "dataset.pano_size=[16,64]", "dataset.batch_size=4",
                          "dataset.val_batch_size=4", "trainer.max_epochs=1", *extra])


@pytest.mark.parametrize("kind,group,name", [("dataset", "dataset", "tiny_folder"), ("backbone", "backbone", "tiny_cnn"),
                                             ("head", "head", "mean_max"), ("loss", "loss", "margin_triplet"),
                                             ("optimizer", "optim", "sgd"), ("sampler", "sampler", "in_order")])
def test_each_kind_is_found_from_its_yaml_and_module(kind, group, name, tmp_path):
    cfg = compose_train([SEARCHPATH, f"{group}={name}", f"dataset.root={tmp_path}", f"run_dir={tmp_path}"])
    assert cfg[group].name == name and cfg[group].module == f"plugins.{name}"
    registry.import_module(cfg[group].module)
    assert name in registry.names(kind)


def test_plugin_components_build_and_compute(tmp_path):
    root = tiny_folder(tmp_path / "folder")
    cfg = plugin_cfg(root, tmp_path / "run")
    split = read_split(cfg.dataset, "val")
    assert split.num_queries == 6 and split.one_to_one and split.queries[0].parent.name == "street"
    task = task_of(cfg)
    assert type(task.model.query.trunk).__name__ == "TinyCNN" and type(task.model.query.head).__name__ == "MeanMaxHead"
    assert type(task.loss).__name__ == "MarginTriplet" and task.loss.margin == 0.2
    (opt,), scheds = task.configure_optimizers()
    assert isinstance(opt, torch.optim.SGD) and scheds == []
    q, r = task.model(torch.randn(3, 3, 32, 32), torch.randn(3, 3, 32, 32))
    assert q.shape == (3, 16) and torch.allclose(q.norm(dim=1), torch.ones(3))


def test_a_plugin_with_a_wrong_argument_fails_at_start_up(tmp_path):
    cfg = compose_train([SEARCHPATH, "loss=margin_triplet", "+loss.margn=0.5", f"run_dir={tmp_path}"])
    with pytest.raises(ConfigError, match=r"loss.margn is not an argument of plugins.margin_triplet.margin_triplet; "
                                          r"its arguments are \['margin'\]"):
        task_of(cfg)


def test_a_missing_plugin_module_is_named(tmp_path):
    cfg = compose_train([SEARCHPATH, "loss=margin_triplet", "loss.module=plugins.no_such_loss", f"run_dir={tmp_path}"])
    with pytest.raises(ConfigError, match="loss.module='plugins.no_such_loss' cannot be imported"):
        task_of(cfg)


def test_a_plugin_given_as_a_file_path(tmp_path):
    """module: may be a path to a .py file instead of an importable module."""
    cfg = compose_train([SEARCHPATH, "head=mean_max", f"head.module={PLUGINS / 'mean_max.py'}", "backbone=tiny_cnn",
                         f"run_dir={tmp_path}", "model.dim=8"])
    assert type(task_of(cfg).model.query.head).__name__ == "MeanMaxHead"


@pytest.mark.slow
def test_train_and_evaluate_with_all_plugins_from_the_command_line(tmp_path):
    """`python train.py` / `python evaluate.py` as a user runs them: six plug-ins, nothing in geoloc edited."""
    root = tiny_folder(tmp_path / "folder")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(PLUGINS.parent), os.environ.get("PYTHONPATH", "")])}
    common = [SEARCHPATH, "trainer.progress=false", "trainer.num_workers=0", "trainer.device=cpu"]
    train = [sys.executable, "train.py", *common, *ALL_PLUGINS, f"dataset.root={root}", "dataset.aerial_size=32",
             "dataset.pano_size=[16,64]", "dataset.batch_size=4", "dataset.val_batch_size=4", "trainer.max_epochs=2",
             "model.dim=16", "figures=false", f"run_dir={tmp_path / 'run'}"]
    done = subprocess.run(train, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "run" / "best.pt").is_file()
    out = tmp_path / "metrics.json"
    evaluate = [sys.executable, "evaluate.py", SEARCHPATH, f"ckpt={tmp_path / 'run' / 'best.pt'}",
                f"metrics_out={out}", "progress=false", f"hydra.run.dir={tmp_path / 'eval'}"]
    done = subprocess.run(evaluate, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    metrics = json.loads(out.read_text())
    assert metrics["num_queries"] == 6 and 0.0 <= metrics["R@1"] <= 1.0


def test_mmdip_takes_a_segmenter_from_outside_the_package(tmp_path):
    """task=mmdip's phase-1 network comes from the same registry (task.segmentation.model + .module)."""
    from geoloc.config import checked
    from geoloc.tasks.mmdip.config import MMDIPConfig
    from geoloc.tasks.mmdip.pipeline import parse
    from geoloc.tasks.mmdip.segmentation import SegmentationTask

    cfg = compose_train(["task=mmdip", "task.segmentation.model=tiny_segmenter",
                         "task.segmentation.module=plugins.tiny_segmenter", f"run_dir={tmp_path}"])
    task_cfg = parse(cfg)[0]
    task = SegmentationTask(task_cfg.segmentation, task_cfg.num_classes, [1 / 8] * 8)
    assert isinstance(task.seg, torch.nn.Conv2d) and task.seg(torch.zeros(1, 3, 16, 16)).shape == (1, 8, 16, 16)
    cfg = compose_train(["task=mmdip", "task.segmentation.model=segformer", f"run_dir={tmp_path}"])
    with pytest.raises(ConfigError, match=r"task.segmentation.model='segformer' is not a known segmenter; choose one "
                                          r"of \[.*'erfnet', 'fcn'"):
        parse(cfg)
    assert checked(cfg.task, MMDIPConfig, "task").segmentation.model == "segformer"  # the name is checked at parse
