"""The defaults of every config section, given to Hydra from their one home: the dataclasses and the registered
factories' signatures.

Each option file under geoloc/conf/ extends one of these nodes and says only what it changes:

    # geoloc/conf/backbone/vgg16_cpu.yaml
    defaults:
      - /schema/backbone/vgg16@_here_   # every key of the vgg16 factory, at its default
      - _self_
    width: 0.125

The nodes are stored in Hydra's ConfigStore under `schema/<section>/<name>`:
- `schema/<name>` for the entry points' own sections: train and evaluate (geoloc.config) and trainer
  (TrainerConfig);
- every node a registered task gives from its `config_nodes()` (group path -> node): the cross-view task's
  components (`schema/backbone/vgg16`: the factory's keyword arguments with their defaults, minus the run-time
  arguments geoloc passes itself), readers (`schema/dataset/cvusa`: the keys every dataset shares, then the
  reader's own), model and gallery; MMDIP's `schema/task/mmdip` and its readers. A node's defaults come from
  geoloc.config.defaults_of (a dataclass) and registry.with_defaults (a factory's signature).
A key missing from a node cannot be set from the command line without `+`, so every key a user may set is in the
composed config, at the value that runs.
"""

from __future__ import annotations

from hydra.core.config_store import ConfigStore

from geoloc import registry
from geoloc.config import defaults_of


def register() -> None:
    """Store every node in Hydra's ConfigStore (idempotent: a second call stores the same nodes again)."""
    import geoloc.tasks  # noqa: F401  (declares the task kind)
    from geoloc.config import EvaluateKeys, TrainKeys
    from geoloc.engine import TrainerConfig

    for section, schema in (("train", TrainKeys), ("evaluate", EvaluateKeys), ("trainer", TrainerConfig)):
        store_dataclass(section, schema)
    store = ConfigStore.instance()
    for name in registry.names("task"):
        nodes = getattr(registry.lookup("task", name), "config_nodes", None)
        for path, node in (nodes() if nodes else {}).items():
            group, _, option = f"schema/{path}".rpartition("/")
            store.store(group=group, name=option, node=node)


def store_dataclass(name: str, schema: type) -> None:
    """Store dataclass `schema`'s defaults as the node `schema/<name>` (an app's entry point stores its own)."""
    ConfigStore.instance().store(group="schema", name=name, node=defaults_of(schema))
