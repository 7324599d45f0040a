"""Turning Hydra config sections into checked dataclasses, so typos and bad values fail at start-up."""

from __future__ import annotations

from typing import Any, TypeVar

from omegaconf import DictConfig, OmegaConf
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


def to_yaml(cfg: Any) -> str:
    return OmegaConf.to_yaml(cfg, resolve=True)
