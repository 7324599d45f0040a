"""Turning Hydra config sections into checked dataclasses, so typos and bad values fail at start-up."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, TypeVar

from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

T = TypeVar("T")


class ConfigError(ValueError):
    pass


def checked(section: DictConfig | dict | None, schema: type[T], where: str) -> T:
    """Merge `section` onto the dataclass `schema`; unknown keys, wrong types and bad values raise ConfigError.

    `where` is the config group (e.g. "dataset"), named in the message so the user knows what to fix.
    """
    if section is None:
        raise ConfigError(f"config group '{where}' is missing")
    base = OmegaConf.structured(schema)
    try:
        if isinstance(section, DictConfig):  # resolve ${...} while the section still sees the root config
            section = OmegaConf.to_container(section, resolve=True)
        merged = OmegaConf.merge(base, section)
        return OmegaConf.to_object(merged)
    except OmegaConfBaseException as err:
        raise ConfigError(f"bad '{where}' config: {err.msg if hasattr(err, 'msg') else err}".strip()) from None
    except ValueError as err:  # __post_init__ checks
        raise ConfigError(f"bad '{where}' config: {err}") from None


def defaults_of(schema: type) -> dict[str, Any]:
    """Every field of dataclass `schema` at its default, as plain config values (a config node's defaults)."""
    return OmegaConf.to_container(OmegaConf.structured(schema), resolve=False)


def to_yaml(cfg: Any) -> str:
    return OmegaConf.to_yaml(cfg, resolve=True)


def top_level(cfg: DictConfig, schema: type[T], where: str) -> T:
    """The fields of dataclass `schema` read from the top level of `cfg` (its other sections are left alone)."""
    return checked({f.name: cfg[f.name] for f in fields(schema) if f.name in cfg}, schema, where)


@dataclass
class TrainKeys:
    """train.py's own keys (the top level of geoloc/conf/train.yaml)."""

    seed: int = 0  # the run's seed: initialisation, sampling and augmentation (dataset.seed picks a synthetic world)
    ckpt: str | None = None  # resume exactly from this last.pt, with the config stored in it
    init_from: str | None = None  # a new run (epoch 0) from this checkpoint's network weights
    figures: bool = True  # the task's pictures after training (cross-view: attention, top-5, recall curve)
    rewind: bool = False  # resume in place from a checkpoint older than the run's last.pt, dropping later epochs


@dataclass
class EvaluateKeys:
    """evaluate.py's own keys (the top level of geoloc/conf/evaluate.yaml)."""

    ckpt: str = MISSING  # the checkpoint to score: a best.pt / last.pt written by train.py
    metrics_out: str | None = None  # write the metrics as JSON to this file
    metrics_out_overwrite: bool = False  # an existing metrics_out file is refused unless this is true
    device: str = "auto"  # auto | cpu | cuda
    num_workers: int = 0  # DataLoader workers
    progress: bool = True
