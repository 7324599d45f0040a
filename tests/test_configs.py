"""Every config composes, and bad values fail at start-up with a message that names the problem."""

from __future__ import annotations

import pytest
from conftest import CONF, compose_evaluate, compose_train
from hydra.errors import MissingConfigException
from omegaconf.errors import MissingMandatoryValue

from geoloc.config import ConfigError, checked
from geoloc.data.crossview import CrossViewDataConfig
from geoloc.engine import TrainerConfig
from geoloc.models.crossview import CrossViewModelConfig
from geoloc.tasks.crossview import OptimConfig, TripletLossConfig

GROUP_SCHEMAS = {"model": CrossViewModelConfig, "loss": TripletLossConfig, "optim": OptimConfig,
                 "trainer": TrainerConfig}


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize("dataset", ["synthetic", "cvusa", "cvact"])
@pytest.mark.parametrize("experiment", [None, *options("experiment")])
def test_every_crossview_config_composes_and_validates(dataset, experiment, tmp_path):
    overrides = [f"dataset={dataset}", f"dataset.root={tmp_path}", f"run_dir={tmp_path}"]
    if experiment:
        overrides.append(f"experiment={experiment}")
    cfg = compose_train(overrides)
    if cfg.task.name != "crossview":
        pytest.skip("experiment for another task")
    checked(cfg.dataset, CrossViewDataConfig, "dataset")
    for group, schema in GROUP_SCHEMAS.items():
        checked(cfg[group], schema, group)


@pytest.mark.parametrize("task", options("task"))
def test_every_task_composes(task, tmp_path):
    cfg = compose_train([f"task={task}", f"run_dir={tmp_path}"])
    assert cfg.task.name == task


def test_evaluate_config_composes():
    cfg = compose_evaluate(["ckpt=x.pt", "dataset.split=test"])
    assert cfg.dataset.split == "test" and cfg.dataset.root is None


def test_unknown_dataset_is_refused():
    with pytest.raises(MissingConfigException, match="dataset"):
        compose_train(["dataset=cvusb"])


def test_typo_key_is_refused():
    cfg = compose_train(["dataset=cvusa", "dataset.root=/x", "+dataset.batchsize=3"])
    with pytest.raises(ConfigError, match="batchsize"):
        checked(cfg.dataset, CrossViewDataConfig, "dataset")


def test_batch_size_zero_is_refused():
    cfg = compose_train(["dataset.batch_size=0"])
    with pytest.raises(ConfigError, match="batch_size must be >= 1"):
        checked(cfg.dataset, CrossViewDataConfig, "dataset")


def test_missing_root_is_refused():
    cfg = compose_train(["dataset=cvusa"])
    with pytest.raises((ConfigError, MissingMandatoryValue), match="root"):
        checked(cfg.dataset, CrossViewDataConfig, "dataset")


def test_bad_alignment_and_precision_are_refused():
    cfg = compose_train(["dataset.alignment=upside_down", "trainer.precision=8"])
    with pytest.raises(ConfigError, match="alignment"):
        checked(cfg.dataset, CrossViewDataConfig, "dataset")
    with pytest.raises(ConfigError, match="precision"):
        checked(cfg.trainer, TrainerConfig, "trainer")


@pytest.mark.parametrize("group,name", [("loss", "infonce"), ("model", "convnext"), ("optim", "sgd")])
def test_a_name_the_task_does_not_build_is_refused(group, name, tmp_path):
    """`loss.name=infonce` used to train the triplet loss without a word: each group's name is now read."""
    from geoloc.tasks.crossview_run import build_task

    cfg = compose_train([f"{group}.name={name}", f"run_dir={tmp_path}"])
    with pytest.raises(ConfigError, match=rf"{group}.name='{name}' .* choose one of"):
        build_task(cfg)
