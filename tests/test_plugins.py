"""Components from outside the geoloc package (tests/plugins/: one .py and one yaml each) plug in from the command
line with no edit to geoloc, one of each kind: for the cross-view task a dataset, a backbone, a head, a loss, an
optimizer and a sampler; for task=mmdip a segmenter, a generator loss and a dataset; and a task itself.

The yaml files live in tests/plugins/conf/<group>/, found through `hydra.searchpath`; each names its module
(`module: plugins.tiny_cnn`), which the registry imports before looking the name up.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from geoloc import registry
from geoloc.config import ConfigError
from geoloc.launch import run
from geoloc.tasks import mmdip
from geoloc.tasks.mmdip.joint import JointTask
from geoloc.tasks.mmdip.pipeline import parse
from geoloc.tasks.mmdip.readers import build_reader
from geoloc.tasks.mmdip.segmentation import SegmentationTask

from conftest import REPO, compose_evaluate, compose_train, write_cvusa
from helpers.crossview_runs import split_of, task_of
from helpers.dynamic_data import TINY_MMDIP, evaluate, write_tiny_dynamic
from helpers.registry_tables import registry_copied

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


@pytest.fixture(autouse=True, scope="module")
def registry_restored_after():
    """What this file's plug-ins register is gone after it: the registry's tables as they were, and the plug-in
    modules forgotten, so a later file in the same process that imports one registers it anew."""
    with pytest.MonkeyPatch.context() as mp:
        registry_copied(mp)
        before = set(sys.modules)
        yield
    for name in set(sys.modules) - before:
        if name == "plugins" or name.startswith("plugins."):
            del sys.modules[name]


QUIET = ["trainer.num_workers=0", "trainer.progress=false", "trainer.device=cpu", "figures=false", "model.dim=16"]


def plugin_cfg(root: Path, run_dir: Path, *extra):
    return compose_train([*QUIET, SEARCHPATH, *ALL_PLUGINS, f"dataset.root={root}", f"run_dir={run_dir}",
                          "dataset.aerial_size=32", "dataset.pano_size=[16,64]", "dataset.batch_size=4",
                          "dataset.val_batch_size=4", "trainer.max_epochs=1", *extra])


@pytest.mark.parametrize("kind,group,name", [("dataset", "dataset", "tiny_folder"), ("backbone", "backbone", "tiny_cnn"),
                                             ("head", "head", "mean_max"), ("loss", "loss", "margin_triplet"),
                                             ("optimizer", "optim", "sgd"), ("sampler", "sampler", "in_order"),
                                             ("mmdip_dataset", "dataset", "image_folders"),
                                             ("task", "task", "fit_mean")])
def test_each_kind_is_found_from_its_yaml_and_module(kind, group, name, tmp_path):
    data_root = [] if kind == "task" else [f"dataset.root={tmp_path}"]  # a plug-in task brings no dataset group
    cfg = compose_train([SEARCHPATH, f"{group}={name}", *data_root, f"run_dir={tmp_path}"])
    assert cfg[group].name == name and cfg[group].module == f"plugins.{name}"
    registry.import_module(cfg[group].module)
    assert name in registry.names(kind)


def test_plugin_components_build_and_compute(tmp_path):
    root = tiny_folder(tmp_path / "folder")
    cfg = plugin_cfg(root, tmp_path / "run")
    split = split_of(cfg.dataset, "val")
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
    """task=mmdip's phase-1 network comes from the same registry (task.segmentation.model + .module), with its own
    keys under task.segmentation.<segmenter>."""
    plugin = ["task=mmdip", "task.segmentation.model=tiny_segmenter", "task.segmentation.module=plugins.tiny_segmenter",
              f"run_dir={tmp_path}"]
    task_cfg = parse(compose_train([*plugin, "+task.segmentation.tiny_segmenter.kernel=5"]))[0]
    task = SegmentationTask(task_cfg.segmentation, task_cfg.num_classes, [1 / 8] * 8)
    assert isinstance(task.seg, torch.nn.Conv2d) and task.seg.kernel_size == (5, 5)
    assert task.seg(torch.zeros(1, 3, 16, 16)).shape == (1, 8, 16, 16)
    with pytest.raises(ConfigError, match=r"task.segmentation.tiny_segmenter.kernl is not an argument of "
                                          r"plugins.tiny_segmenter.tiny_segmenter; its arguments are \['kernel'\]"):
        parse(compose_train([*plugin, "+task.segmentation.tiny_segmenter.kernl=5"]))
    cfg = compose_train(["task=mmdip", "task.segmentation.model=segformer", f"run_dir={tmp_path}"])
    with pytest.raises(ConfigError, match=r"task.segmentation.model='segformer' is not a known segmenter; choose one "
                                          r"of \[.*'erfnet', 'fcn'"):
        parse(cfg)


class StubEngine:
    """What JointTask.training_step asks of the trainer, on the CPU in fp32."""

    autocast = staticmethod(contextlib.nullcontext)

    def backward(self, loss):
        loss.backward()

    def step(self, optimizer):
        optimizer.step()
        optimizer.zero_grad()


def test_mmdip_takes_a_generator_loss_from_outside_the_package(tmp_path):
    """task.translation.generator_loss names a registered loss; plugins/l1_hinge.py replaces eq. 2's weighted sum."""
    plugin = ["task=mmdip", "task.translation.generator_loss.name=l1_hinge",
              "+task.translation.generator_loss.module=plugins.l1_hinge", "+task.translation.generator_loss.l1=5",
              "task.translation.num_downs=3", "task.translation.ngf=4", "task.translation.ndf=4",
              "task.translation.d_layers=1", f"run_dir={tmp_path}"]
    task_cfg = parse(compose_train(plugin))[0]
    torch.manual_seed(0)
    task = JointTask(task_cfg, [1 / 8] * 8)
    assert type(task.generator_loss).__name__ == "L1Hinge" and task.generator_loss.l1 == 5
    task.configure_optimizers()
    batch = {"dynamic": torch.rand(2, 3, 16, 16), "static": torch.rand(2, 3, 16, 16),
             "label": torch.randint(0, 8, (2, 16, 16)), "index": torch.arange(2)}
    out = task.training_step(batch, StubEngine())
    assert set(out) == {"loss", "d_loss", "g_adv", "l1", "ce"}  # the plug-in's terms, no perceptual one
    assert out["loss"] == pytest.approx(float(out["g_adv"] + 5 * out["l1"] + out["ce"]), rel=1e-5)
    with pytest.raises(ConfigError, match=r"task.translation.generator_loss.l2 is not an argument of "
                                          r"plugins.l1_hinge.l1_hinge; its arguments are \['l1'\]"):
        parse(compose_train([*plugin, "+task.translation.generator_loss.l2=5"]))


def image_folders(src: Path, out: Path) -> Path:
    """The image_folders plug-in's layout, written from a tiny `dynamic` layout: each query view is a place."""
    for split in ("train", "val"):
        rows = [line.split(",") for line in (src / "splits" / f"{split}.csv").read_text().splitlines()[1:]]
        for sample in (row[0] for row in rows if row[2] == "query"):
            for kind, folder in (("dynamic", "rgb_dynamic"), ("static", "rgb_static"), ("mask", "mask_dynamic"),
                                 ("label", "label_static")):
                (out / split / kind).mkdir(parents=True, exist_ok=True)
                (out / split / kind / f"{sample}.png").write_bytes((src / folder / f"{sample}.png").read_bytes())
    return out


def test_mmdip_reads_a_dataset_from_outside_the_package(tmp_path):
    """dataset.name picks a registered reader; plugins/image_folders.py gives the splits, the place protocol and
    the class fractions, and its own keys are checked against its signature."""
    root = image_folders(write_tiny_dynamic(tmp_path / "dyn", n_train=2, n_val=3), tmp_path / "folders")
    cfg = compose_train(["task=mmdip", SEARCHPATH, "dataset=image_folders", f"dataset.root={root}",
                         f"run_dir={tmp_path}"])
    data_cfg = parse(cfg)[1]
    reader = build_reader(data_cfg)
    assert type(reader).__module__ == "plugins.image_folders"
    item = reader.split("train", train=True)[(1, 0)]
    assert item["dynamic"].shape == item["static"].shape == (3, 64, 64) and item["label"].shape == (64, 64)
    protocol = reader.place_protocol("val")
    assert len(protocol.queries) == 3 and protocol.folder == root / "val" and len(protocol.vocabulary) == 2
    labels = np.stack([reader.split("train")[i]["label"].numpy() for i in range(2)])
    assert reader.class_fractions() == pytest.approx(np.bincount(labels.ravel(), minlength=8) / labels.size, abs=1e-6)
    with pytest.raises(ConfigError, match=r"dataset.extension is not an argument of plugins.image_folders"):
        parse(compose_train(["task=mmdip", SEARCHPATH, "dataset=image_folders", f"dataset.root={root}",
                             "+dataset.extension=.jpg", f"run_dir={tmp_path}"]))


@pytest.mark.slow
def test_mmdip_trains_and_evaluates_on_a_dataset_from_outside_the_package(tmp_path, one_thread):
    root = image_folders(write_tiny_dynamic(tmp_path / "dyn", n_train=2, n_val=4), tmp_path / "folders")
    overrides = [*TINY_MMDIP, SEARCHPATH, "dataset=image_folders", f"dataset.root={root}"]
    result = mmdip.train(compose_train([*overrides, f"run_dir={tmp_path / 'run'}"]), tmp_path / "run")
    assert result["num_queries"] == 4 and 0 <= result["R@1"] <= 1
    again = evaluate(compose_train(overrides), tmp_path / "run" / "phase2" / "best.pt")
    assert {k: again[k] for k in ("R@1", "R@5")} == {k: result[k] for k in ("R@1", "R@5")}


def test_a_task_from_outside_the_package_trains_and_evaluates(tmp_path):
    """task.name finds a registered task (plugins/fit_mean.py, imported from task.module) for training, and the
    checkpoint's stored task.name finds it again for evaluation."""
    best = run.train(compose_train([SEARCHPATH, "task=fit_mean", "trainer.progress=false", "trainer.device=cpu",
                                    f"run_dir={tmp_path / 'run'}"]))
    assert best["error"] < 3.5  # the mean of 0..7 is 3.5; the fitted number starts at 0
    metrics = run.evaluate(compose_evaluate([f"ckpt={tmp_path / 'run' / 'best.pt'}", "device=cpu"]))
    assert metrics["error"] == pytest.approx(best["error"], abs=1e-6)
    with pytest.raises(ConfigError, match=r"task.name='fit_men' is not a known task; choose one of "
                                          r"\['crossview', 'fit_mean', 'mmdip'\]"):
        run.train(compose_train([SEARCHPATH, "task=fit_mean", "task.name=fit_men", f"run_dir={tmp_path / 'x'}"]))


@pytest.mark.slow
def test_a_task_from_outside_the_package_runs_from_the_command_line(tmp_path):
    """`python train.py task=fit_mean` / `python evaluate.py ckpt=...`, nothing in geoloc edited."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(PLUGINS.parent), os.environ.get("PYTHONPATH", "")])}
    train = [sys.executable, "train.py", SEARCHPATH, "task=fit_mean", "trainer.progress=false", "trainer.device=cpu",
             f"hydra.run.dir={tmp_path / 'run'}"]
    done = subprocess.run(train, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    out = tmp_path / "metrics.json"
    evaluate = [sys.executable, "evaluate.py", f"ckpt={tmp_path / 'run' / 'best.pt'}", f"metrics_out={out}",
                f"hydra.run.dir={tmp_path / 'eval'}"]
    done = subprocess.run(evaluate, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads(out.read_text())["error"] < 3.5
