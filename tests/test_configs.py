"""Every config composes and builds, and bad values fail at start-up with a message that names the problem."""

from __future__ import annotations

import pytest
from geoloc import registry
from geoloc.config import ConfigError, checked
from geoloc.engine import TrainerConfig
from geoloc.tasks.crossview.data_config import CrossViewDataConfig, parse_dataset

from hydra.errors import MissingConfigException

from conftest import CONF, compose_evaluate, compose_train
from helpers.crossview_runs import split_of, task_of

SMALL_NETWORK = ["backbone.width=0.125", "backbone.pretrained=false", "model.dim=32"]


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize("dataset", ["synthetic", "cvusa", "cvact", "vigor", "u1652"])
@pytest.mark.parametrize("experiment", [None, *options("experiment")])
def test_every_crossview_config_composes_and_builds(dataset, experiment, tmp_path):
    overrides = [f"dataset={dataset}", f"dataset.root={tmp_path}", f"run_dir={tmp_path}"]
    if experiment:
        overrides.append(f"experiment={experiment}")
    cfg = compose_train(overrides)
    if cfg.task.name != "crossview":
        pytest.skip("experiment for another task")
    parse_dataset(cfg.dataset)[0]
    checked(cfg.trainer, TrainerConfig, "trainer")
    registry.check_arguments(registry.lookup("dataset", cfg.dataset.name),
                             {k: v for k, v in cfg.dataset.items() if k not in CrossViewDataConfig.__dataclass_fields__},
                             {"root": None, "split": "train"}, cfg.dataset.name, "dataset")
    if cfg.backbone.pretrained:  # no ImageNet file here: the same network, untrained (and thinner for VGG16)
        thinner = (["backbone.width=0.125", "model.dim=64"] if cfg.backbone.name == "vgg16" else
                   ["backbone.model_args={dims:[8,16,32,64],depths:[1,1,1,1]}"])
        cfg = compose_train([*overrides, "backbone.pretrained=false", *thinner])
    task_of(cfg)


@pytest.mark.parametrize("group", ["backbone", "head", "loss", "optim", "sampler"])
def test_every_group_option_builds(group, tmp_path):
    for option in options(group):
        small = SMALL_NETWORK if group != "backbone" or option.startswith("vgg16") else [
            "backbone.pretrained=false", "backbone.model_args={dims:[8,16,32,64],depths:[1,1,1,1]}"]
        task = task_of(compose_train([f"{group}={option}", f"run_dir={tmp_path}", *small]))
        task.configure_optimizers()


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


def test_typo_in_a_shared_dataset_key_is_refused():
    cfg = compose_train(["dataset=cvusa", "dataset.root=/x", "+dataset.batchsize=3"])
    with pytest.raises(ConfigError, match="batchsize"):
        split_of(cfg.dataset, "train")


def test_typo_in_a_reader_key_is_refused_before_anything_is_read(tmp_path):
    """VIGOR's own keys go to its reader, whose signature names the ones it takes; nothing is generated."""
    cfg = compose_train(["dataset=vigor", f"dataset.root={tmp_path / 'none'}", "+dataset.settting=cross_area"])
    with pytest.raises(ConfigError, match=r"dataset.settting is not an argument .* \[.*'setting'"):
        split_of(cfg.dataset, "train")
    assert not (tmp_path / "none").exists()


def test_batch_size_zero_is_refused():
    cfg = compose_train(["dataset.batch_size=0"])
    with pytest.raises(ConfigError, match="batch_size must be >= 1"):
        parse_dataset(cfg.dataset)[0]


def test_missing_root_is_refused():
    cfg = compose_train(["dataset=cvusa"])
    with pytest.raises(ConfigError, match="dataset.root"):
        split_of(cfg.dataset, "train")


def test_bad_alignment_and_precision_are_refused():
    cfg = compose_train(["dataset.alignment=upside_down", "trainer.precision=8"])
    with pytest.raises(ConfigError, match="alignment"):
        parse_dataset(cfg.dataset)[0]
    with pytest.raises(ConfigError, match="precision"):
        checked(cfg.trainer, TrainerConfig, "trainer")


@pytest.mark.parametrize("group,name", [("loss", "infonse"), ("backbone", "convnxt"), ("head", "attention"),
                                        ("optim", "sgd")])
def test_an_unknown_name_is_refused_with_the_choices(group, name, tmp_path):
    """`loss.name=infonce` once trained the triplet loss without a word: each name is looked up, or refused."""
    cfg = compose_train([f"{group}.name={name}", f"run_dir={tmp_path}"])
    with pytest.raises(ConfigError, match=rf"{group}.name='{name}' is not a known .* choose one of \["):
        task_of(cfg)


@pytest.mark.parametrize("override,key", [("+loss.margin=0.3", "loss.margin"), ("+head.heads=4", "head.heads"),
                                          ("+backbone.depth=3", "backbone.depth"), ("+optim.momentum=0.9",
                                                                                     "optim.momentum")])
def test_an_argument_the_component_does_not_take_is_refused(override, key, tmp_path):
    cfg = compose_train([override, f"run_dir={tmp_path}"])
    with pytest.raises(ConfigError, match=rf"{key} is not an argument of .*; its arguments are \["):
        task_of(cfg)


def test_a_runtime_argument_cannot_be_set_from_config(tmp_path):
    cfg = compose_train(["+head.in_channels=[3]", f"run_dir={tmp_path}"])
    with pytest.raises(ConfigError, match="head.in_channels is set by geoloc at run time"):
        task_of(cfg)


def test_ablations_apply_on_top_of_an_experiment(tmp_path):
    """ablation= comes after experiment= in train.yaml: the paper recipe with a Table 2 row is that row."""
    cfg = compose_train(["experiment=paper_cvusa", "ablation=no_msae", "dataset.root=/x"])
    assert cfg.head.name == "fc" and cfg.head.proj_channels == 64 and cfg.backbone.width == 1.0
    cfg = compose_train(["experiment=paper_cvusa", "ablation=no_gms", "dataset.root=/x"])
    assert cfg.loss.queue_size == 0
    cfg = compose_train(["experiment=paper_cvusa", "ablation=no_ipt", "dataset.root=/x"])
    assert cfg.dataset.alignment == "none"


def test_command_line_groups_replace_the_default_experiments_choices():
    cfg = compose_train(["loss=infonce", "head=gap", "optim=adamw"])
    assert cfg.loss.name == "infonce" and "queue_size" not in cfg.loss
    assert cfg.head.name == "gap" and list(cfg.head) == ["name"]
    assert cfg.optim.name == "adamw" and "step_size" not in cfg.optim
    assert cfg.model.dim == 256 and cfg.dataset.aerial_size == 64  # the rest of the CPU recipe stays
