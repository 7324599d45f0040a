"""The defaults of every config section, given to Hydra from their one home: the dataclasses and the registered
factories' signatures.

Each option file under conf/ extends one of these nodes and says only what it changes:

    # conf/backbone/vgg16_cpu.yaml
    defaults:
      - /schema/backbone/vgg16@_here_   # every key of the vgg16 factory, at its default
      - _self_
    width: 0.125

The nodes are stored in Hydra's ConfigStore under `schema/<section>/<name>`:
- `schema/<group>/<factory>` for every registered component (backbone, head, loss, optim, sampler): the factory's
  keyword arguments with their defaults, minus the run-time arguments geoloc passes itself;
- `schema/dataset/<reader>` for every registered cross-view reader: CrossViewDataConfig's fields (the keys every
  dataset shares) and the reader's own keyword arguments;
- `schema/<name>` for the fixed sections: train and evaluate (the entry points' own keys: geoloc.config),
  trainer (TrainerConfig), model (CrossViewModelConfig), gallery (GalleryConfig).
A key missing from a node cannot be set from the command line without `+`, so every key a user may set is in the
composed config, at the value that runs.
"""

from __future__ import annotations

from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from geoloc import registry



def dataclass_defaults(schema: type) -> dict[str, Any]:
    """Every field of a dataclass at its default, as plain config values."""
    return OmegaConf.to_container(OmegaConf.structured(schema), resolve=False)


def factory_defaults(kind: str, name: str) -> dict[str, Any]:
    """{"name": name, **the factory's config keys at their defaults} of registered component `name`."""
    return registry.with_defaults(kind, {"name": name})


def reader_defaults(name: str) -> dict[str, Any]:
    """The dataset node of cross-view reader `name`: the shared keys, then the reader's own."""
    from geoloc.tasks.crossview.data_config import CrossViewDataConfig

    return {**dataclass_defaults(CrossViewDataConfig), **factory_defaults("dataset", name)}


def register() -> None:
    """Store every node in Hydra's ConfigStore (idempotent: a second call stores the same nodes again)."""
    from geoloc.config import EvaluateKeys, TrainKeys
    from geoloc.engine import TrainerConfig
    from geoloc.models.crossview import CrossViewModelConfig
    from geoloc.tasks.crossview.config import COMPONENTS
    from geoloc.tasks.crossview.gallery import GalleryConfig

    store = ConfigStore.instance()
    for kind in COMPONENTS:
        for name in registry.names(kind):
            store.store(group=f"schema/{registry.section(kind)}", name=name, node=factory_defaults(kind, name))
    for name in registry.names("dataset"):
        store.store(group="schema/dataset", name=name, node=reader_defaults(name))
    for section, schema in (("train", TrainKeys), ("evaluate", EvaluateKeys), ("trainer", TrainerConfig),
                            ("model", CrossViewModelConfig), ("gallery", GalleryConfig)):
        store_dataclass(section, schema)


def store_dataclass(name: str, schema: type) -> None:
    """Store dataclass `schema`'s defaults as the node `schema/<name>` (an app's entry point stores its own)."""
    ConfigStore.instance().store(group="schema", name=name, node=dataclass_defaults(schema))
