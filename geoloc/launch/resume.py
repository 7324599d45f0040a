"""`ckpt=` resumes a run exactly, with the config stored in the checkpoint, or refuses.

    python train.py ckpt=RUN/last.pt hydra.run.dir=RUN trainer.max_epochs=30

The run trains with the stored config, whatever the command line composed around it; only the keys a resume may
change are taken from the command line: this module's RESUME_MAY_CHANGE (the engine's and the launcher's keys)
plus the task's own (a task package's RESUME_MAY_CHANGE). Another key the command line sets to a value other than
the stored one is refused by name, so the saved record of what ran stays true. Configs are compared in the task's
canonical form (`canonical_config`: the parsed config with every default filled in), so a key added to the code
since the checkpoint was written, at the default that computes what ran before it existed, is no difference.

A resume in place (`hydra.run.dir` = the checkpoint's folder) from a checkpoint older than the folder's last.pt
would drop the later epochs from last.pt and metrics.jsonl: it is refused, naming both epochs, unless `rewind=true`.

`init_from=PATH` is a new run (fine-tuning, new data, new lr) that loads the network weights only:
geoloc.engine.checkpoint.init_from.
"""

from __future__ import annotations

from pathlib import Path
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
    "run_dir", "ckpt", "init_from", "rewind", "hydra",  # where the run writes and what it starts from
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


def given_keys(overrides: list[str]) -> list[str]:
    """The config keys command-line overrides set: `a.b=1`, `+a.b=1`, `~a.b` -> "a.b"; `dataset=cvusa` -> "dataset"."""
    keys = []
    for override in overrides:
        key = override.split("=", 1)[0].lstrip("+~")
        keys.append(key.split("@", 1)[0])
    return keys


def resumed_config(cfg: DictConfig, task_may_change: tuple[str, ...] = (),
                   canonical: Callable[[DictConfig], dict] | None = None,
                   given: list[str] | None = None) -> DictConfig:
    """The config a `ckpt=` resume trains with (module docstring). `given`: the command line's overrides, as
    Hydra records them; None when unknown (a config composed in code), and then every difference is refused."""
    path = cfg.ckpt
    if cfg.get("init_from"):
        raise ConfigError(f"ckpt={path} and init_from={cfg.init_from} were both given: ckpt= continues a run "
                          f"exactly, init_from= starts a new one from its weights. Pass one of them.")
    state = ckpt_io.load(path)
    if not state.get("config"):
        raise ConfigError(f"checkpoint {path} holds no config, so it cannot be resumed exactly; start a new run "
                          f"from its weights with init_from={path} instead of ckpt=.")
    refuse_rewind(cfg, state)
    stored = OmegaConf.create(state["config"])
    as_compared = canonical or (lambda c: OmegaConf.to_container(c, resolve=True))
    allowed = RESUME_MAY_CHANGE + tuple(task_may_change)
    differences = config_differences(as_compared(stored), as_compared(cfg), allowed)
    if given is not None:
        keys = given_keys(given)
        differences = [d for d in differences if may_change(d.split(":", 1)[0], tuple(keys))]
    if differences:
        lines = "\n  ".join(differences)
        raise ConfigError(
            f"ckpt={path} resumes the run with the config stored in it, and the command line changes these keys "
            f"(stored → requested):\n  {lines}\nDrop those overrides to resume exactly (the stored config is in the "
            f"checkpoint and in the run's .hydra/config.yaml), or start a new run from these weights with "
            f"init_from={path} instead of ckpt=. A resume may change only: {', '.join(allowed)}.")
    # what the resume takes from the request: where it runs and from what, and the allowed keys the command line
    # gave (all allowed keys the stored config holds, when the command line is unknown)
    taken = ("run_dir", "ckpt", "init_from", "rewind") + (tuple(given_keys(given)) if given is not None else allowed)
    held = flat(OmegaConf.to_container(stored, resolve=True))
    resumed = stored
    for key, value in flat(OmegaConf.to_container(cfg, resolve=True)).items():
        if may_change(key, allowed) and may_change(key, taken) and not may_change(key, ("hydra",)) and (
                key in held or key in taken):
            OmegaConf.update(resumed, key, value, force_add=True)
    return resumed


def refuse_rewind(cfg: DictConfig, state: dict) -> None:
    """A resume in place from a checkpoint older than the run dir's last.pt is refused unless `rewind=true`."""
    run_dir = OmegaConf.select(cfg, "run_dir", throw_on_resolution_failure=False)
    if not run_dir or cfg.get("rewind", False):
        return
    last = Path(run_dir) / "last.pt"
    ckpt = Path(cfg.ckpt)
    if not last.is_file() or ckpt.resolve() == last.resolve():
        return
    last_epoch = ckpt_io.load(last).get("epoch")
    if last_epoch is not None and state.get("epoch") is not None and last_epoch > state["epoch"]:
        raise ConfigError(
            f"ckpt={ckpt} is from epoch {state['epoch']}, but {last} in the run dir {run_dir} is from epoch "
            f"{last_epoch}: resuming here would replace last.pt and drop epochs {state['epoch'] + 1}..{last_epoch} "
            f"from metrics.jsonl. Resume from {last}, resume into a new run dir (leave hydra.run.dir at its "
            f"default), or pass rewind=true to go back to epoch {state['epoch']} on purpose.")
