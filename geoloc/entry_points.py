"""The Hydra entry points of `geoloc train | evaluate | localize | export`, inside the package with their configs
(geoloc/conf/, package data), so a wheel trains without a checkout. train.py, evaluate.py, localize.py and export.py
at the repository's root are thin callers of these, with the same keys.

Each composes `geoloc/conf/<verb>.yaml` with the command line's overrides; a refusal (ConfigError, a taken run dir,
a missing file) prints one line (refusal.py)."""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

import geoloc.launch.hydra_hooks  # noqa: F401  (the schema nodes every geoloc/conf/ file extends, and ${pid:})
from geoloc.launch.refusal import refusals_in_one_line

CONF = "conf"  # geoloc/conf, relative to this file as Hydra reads config_path


@hydra.main(version_base="1.3", config_path=CONF, config_name="train")
def _train(cfg: DictConfig) -> float:
    from geoloc.launch.run import objective, train

    with refusals_in_one_line():  # a ConfigError: one line, no traceback (HYDRA_FULL_ERROR=1 shows it)
        return objective(cfg, train(cfg))  # the value Hydra sweepers optimise (the task's sweep_metric)


@hydra.main(version_base="1.3", config_path=CONF, config_name="evaluate")
def _evaluate(cfg: DictConfig) -> None:
    from geoloc.launch.run import evaluate

    with refusals_in_one_line():
        evaluate(cfg)


@hydra.main(version_base="1.3", config_path=CONF, config_name="localize")
def _localize(cfg: DictConfig) -> None:
    from geoloc.apps.localize.command import localize

    with refusals_in_one_line():
        localize(cfg)


@hydra.main(version_base="1.3", config_path=CONF, config_name="export")
def _export(cfg: DictConfig) -> None:
    from geoloc.apps.export.onnx_export import export

    with refusals_in_one_line():
        export(cfg)


def train() -> None:
    """`python train.py ...` / `geoloc train ...` (torchrun ranks above 0 share rank 0's run dir and write nothing)."""
    from geoloc.launch.hydra_hooks import hydra_overrides_for_rank

    sys.argv += hydra_overrides_for_rank()
    _train()


def evaluate() -> None:
    _evaluate()


def localize() -> None:
    from geoloc.apps.localize.command import LocalizeConfig
    from geoloc.launch.schemas import store_dataclass

    store_dataclass("localize", LocalizeConfig)  # the defaults geoloc/conf/localize.yaml extends
    _localize()


def export() -> None:
    _export()


VERBS = {"train": train, "evaluate": evaluate, "localize": localize, "export": export}
