"""The defaults geoloc/conf/ extends for task=mmdip (geoloc/launch/schemas.py stores them), from their one home."""

from __future__ import annotations

from geoloc import registry
from geoloc.config import defaults_of
from geoloc.tasks.mmdip import readers  # noqa: F401  (declares the mmdip_dataset kind)
from geoloc.tasks.mmdip.mmdip_config import DynamicDataConfig, MMDIPConfig


def config_nodes() -> dict[str, dict]:
    """`task/mmdip` (MMDIPConfig) and `dataset/<reader>` for every registered reader (DynamicDataConfig's shared
    keys, then the reader's own from its signature)."""
    task = defaults_of(MMDIPConfig)
    del task["segmentation"]["segmenter_keys"]  # a segmenter's keys are written task.segmentation.<segmenter>.<key>
    shared = {k: v for k, v in defaults_of(DynamicDataConfig).items() if k != "reader_keys"}
    by_reader = {f"dataset/{name}": {**shared, **registry.with_defaults("mmdip_dataset", {"name": name})}
                for name in registry.names("mmdip_dataset")}
    return {"task/mmdip": task, **by_reader}
