"""`ckpt=` resumes a run exactly or refuses: only with the config stored in the checkpoint.

A key outside the allow-list whose value differs fails with the list of differences, so the saved record of what
ran stays true. The allow-list is this module's RESUME_MAY_CHANGE (the engine's and the launcher's keys) plus the
task's own (a task package's RESUME_MAY_CHANGE). Both configs are compared in the task's canonical form
(`canonical_config`: the parsed config with every default filled in), so a key added to the code since the
checkpoint was written, at the default that computes what ran before it existed, is no difference.

`init_from=PATH` is a new run (fine-tuning, new data, new lr) that loads the network weights only:
geoloc.engine.checkpoint.init_from.
"""

from __future__ import annotations

from typing import Any, Callable

from omegaconf import DictConfig, OmegaConf

from geoloc.config import ConfigError
from geoloc.engine import checkpoint as ckpt_io

#: Config keys (and key prefixes) a resume may change whatever the task, because they cannot change what is computed.
RESUME_MAY_CHANGE = (
    "trainer.max_epochs",  # more epochs: the epochs already run are not run again
    "trainer.num_workers", "trainer.pin_memory", "trainer.persistent_workers",  # loading only: samples are keyed
    "trainer.device",  # moving a run to another machine
    "trainer.progress", "trainer.log_every_n_steps", "figures",  # what is shown and logged
    "run_dir", "ckpt", "init_from", "hydra",  # where the run writes and what it starts from
)


def flat(tree: Any, prefix: str = "") -> dict[str, Any]:
    """{"a": {"b": 1}} -> {"a.b": 1}; lists stay whole values."""
    if not isinstance(tree, dict) or not tree:
        return {prefix: tree}
    out: dict[str, Any] = {}
    for key, value in tree.items():
        out.update(flat(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def may_change(key: str, allowed: tuple[str, ...]) -> bool:
    return any(key == a or key.startswith(a + ".") for a in allowed)


def config_differences(stored: dict, requested: dict, allowed: tuple[str, ...] = RESUME_MAY_CHANGE) -> list[str]:
    """'key: stored -> requested' for every key outside `allowed` whose value differs."""
    old, new = flat(stored), flat(requested)
    absent = "(absent)"
    return [f"{key}: {old.get(key, absent)} → {new.get(key, absent)}" for key in sorted(old.keys() | new.keys())
            if not may_change(key, allowed) and old.get(key, absent) != new.get(key, absent)]


def checked_resume(cfg: DictConfig, task_may_change: tuple[str, ...] = (),
                   canonical: Callable[[DictConfig], dict] | None = None) -> None:
    """Refuse `ckpt=` when the requested config differs from the checkpoint's outside the allow-list (module
    docstring). `canonical` maps a config to the form both are compared in (default: the config as written)."""
    path = cfg.ckpt
    if cfg.get("init_from"):
        raise ConfigError(f"ckpt={path} and init_from={cfg.init_from} were both given: ckpt= continues a run "
                          f"exactly, init_from= starts a new one from its weights. Pass one of them.")
    stored = ckpt_io.load(path).get("config")
    if not stored:
        raise ConfigError(f"checkpoint {path} holds no config, so it cannot be resumed exactly; start a new run "
                          f"from its weights with init_from={path} instead of ckpt=.")
    as_compared = canonical or (lambda c: OmegaConf.to_container(c, resolve=True))
    allowed = RESUME_MAY_CHANGE + tuple(task_may_change)
    differences = config_differences(as_compared(OmegaConf.create(stored)), as_compared(cfg), allowed)
    if differences:
        lines = "\n  ".join(differences)
        raise ConfigError(
            f"ckpt={path} resumes only with the config it was trained with, and these keys differ (stored → "
            f"requested):\n  {lines}\nDrop those overrides to resume exactly (the stored config is in the "
            f"checkpoint and in the run's .hydra/config.yaml), or start a new run from these weights with "
            f"init_from={path} instead of ckpt=. A resume may change only: {', '.join(allowed)}.")
