"""Every config composes and builds, and bad values fail at start-up with a message that names the problem."""

from __future__ import annotations

import pytest
import torch
from geoloc import registry
from geoloc.config import ConfigError, checked
from geoloc.engine import TrainerConfig
from geoloc.models.packaged_weights import is_packaged
from geoloc.models.unfilled_init import unfilled_init
from geoloc.tasks.crossview.data_config import parse_dataset

from hydra.errors import MissingConfigException

from conftest import CONF, compose_evaluate, compose_train
from helpers.crossview_runs import split_of, task_of

SMALL_NETWORK = ["backbone.width=0.125", "backbone.pretrained=false", "model.dim=32"]


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


GROUPS = sorted(p.name for p in CONF.iterdir() if p.is_dir() and p.name != "hydra")


def every_option() -> list[tuple[str, str]]:
    return [(group, option) for group in GROUPS for option in options(group)]


@pytest.fixture(scope="module")
def imagenet_stand_in(tmp_path_factory) -> dict:
    """Test state dicts standing in for the ImageNet files a paper option reads (nothing is downloaded): a
    torchvision-layout VGG16 `features.*` dict for the trunk, and a features-only one for MMDIP's perceptual loss."""
    from geoloc.losses.perceptual import vgg16_features

    folder = tmp_path_factory.mktemp("weights")
    torch.manual_seed(0)
    features = vgg16_features(30)  # conv5_3's ReLU: every conv of the trunk
    torch.save({f"features.{k}": v for k, v in features.state_dict().items()}, folder / "vgg16.pth")
    torch.save(vgg16_features(16).state_dict(), folder / "vgg16_features.pth")
    return {"trunk": folder / "vgg16.pth", "perceptual": folder / "vgg16_features.pth"}


def task_of_option(group: str, option: str) -> str:
    """The task an option belongs to: a task option is its own; an experiment says it; a dataset its reader's
    registry; every other group is one the cross-view task brings."""
    if group == "task":
        return option
    if group == "experiment":
        return str(compose_train([f"experiment={option}"]).task.name)
    if group == "dataset" and option not in registry.names("dataset"):
        return "mmdip"
    return "crossview"


@pytest.mark.slow
@pytest.mark.parametrize("group,option", every_option())
def test_every_option_of_every_group_composes_and_builds(group, option, imagenet_stand_in, tmp_path):
    """Each option of each geoloc/conf/ group composes for its task and builds what it configures, offline.

    The networks are built under unfilled_init (no random initial weights drawn: what the test checks is that every
    layer, shape and weight file of the option builds and loads, not torch's fills), 4 s faster for each VGG16."""
    task = task_of_option(group, option)
    overrides = [f"{group}={option}", f"run_dir={tmp_path}"]
    if task == "mmdip" and group not in ("task", "experiment"):
        overrides.insert(0, "task=mmdip")
    cfg = compose_train(overrides)
    assert cfg.task.name == task
    if cfg.dataset.get("root") in (None, "???") and cfg.dataset.name not in ("synthetic", "vigor", "u1652",
                                                                              "dynamic"):
        cfg = compose_train([*overrides, f"dataset.root={tmp_path}"])
    if task == "mmdip":
        from geoloc.tasks.mmdip.joint import JointTask
        from geoloc.tasks.mmdip.pipeline import parse
        from geoloc.tasks.mmdip.segmentation import SegmentationTask

        weights = cfg.task.translation.perceptual_weights
        if weights != "none":
            cfg = compose_train([*overrides, f"task.translation.perceptual_weights={imagenet_stand_in['perceptual']}"])
        if cfg.dataset.name == "emptycities":  # an evaluation-only reader: refused for training, read by evaluate
            with pytest.raises(ConfigError, match="for evaluation only"):
                parse(cfg)
            from geoloc.tasks.mmdip.mmdip_config import DynamicDataConfig

            evaluation = compose_evaluate(["ckpt=x.pt", "dataset=emptycities", f"dataset.root={tmp_path}"])
            asked = {k: v for k, v in evaluation.dataset.items() if v is not None}  # null = as trained
            checked(asked, DynamicDataConfig, "dataset")
            return
        task_cfg, _, _ = parse(cfg)
        uniform = [1 / task_cfg.num_classes] * task_cfg.num_classes
        with unfilled_init():
            SegmentationTask(task_cfg.segmentation, task_cfg.num_classes, uniform).configure_optimizers()
            JointTask(task_cfg, uniform).configure_optimizers()
        return
    if cfg.backbone.get("pretrained") and not is_packaged(cfg.backbone.get("weights_path")):
        # ImageNet's files are not here; weights shipped in the package (geoloc:NAME) are, and load as they are
        stand_in = ([f"backbone.weights_path={imagenet_stand_in['trunk']}"] if cfg.backbone.name == "vgg16" else
                    ["backbone.pretrained=false", "backbone.model_args={dims:[8,16,32,64],depths:[1,1,1,1]}"])
        cfg = compose_train([*overrides, *stand_in] + ([f"dataset.root={tmp_path}"] if "root=" not in str(
            overrides) and cfg.dataset.get("root") not in (None,) else []))
    with unfilled_init():
        task_of(cfg).configure_optimizers()


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
