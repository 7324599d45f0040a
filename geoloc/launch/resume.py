"""How a run starts from a checkpoint: `ckpt=` resumes it exactly or refuses; `init_from=` starts a new run from
its network weights.

- `ckpt=RUN/last.pt` continues that run: model, optimizer, scheduler, scaler, GMS queue, epoch, best, RNG states.
  It resumes only with the config stored in the checkpoint; a key outside `RESUME_MAY_CHANGE` that differs fails
  with the list of differences, so the saved record of what ran stays true (a key added since, `ADDED_KEYS`, may
  be requested at the value that computes what ran before it existed).
- `init_from=PATH` is a new run (fine-tuning, new data, new lr): it loads the network weights only and starts at
  epoch 0 with a fresh optimizer, scheduler, best metric and GMS queue (the queue's descriptors and place ids
  belong to the source run's data). Where the weights came from goes to `init_from.json` and into its checkpoints.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from geoloc.config import ConfigError
from geoloc.engine import checkpoint as ckpt_io

#: Config keys (and key prefixes) a resume may change, because they cannot change what is computed.
RESUME_MAY_CHANGE = (
    "trainer.max_epochs",  # more epochs: the epochs already run are not run again
    "trainer.num_workers", "trainer.pin_memory", "trainer.persistent_workers",  # loading only: samples are keyed
    "trainer.device",  # moving a run to another machine
    "trainer.progress", "trainer.log_every_n_steps", "figures",  # what is shown and logged
    "run_dir", "ckpt", "init_from", "hydra",  # where the run writes and what it starts from
    "dataset.workers",  # processes that render the synthetic set: the same files either way
)

#: Keys added to the config after checkpoints were written, each with the value that computes what ran before it
#: existed: a checkpoint without the key resumes when the request holds exactly that value.
ADDED_KEYS = {
    "dataset.fov": 360.0, "dataset.random_heading": False, "dataset.heading_steps": 36,  # issue 12 (heading)
}


def flat(tree: Any, prefix: str = "") -> dict[str, Any]:
    """{"a": {"b": 1}} -> {"a.b": 1}; lists stay whole values."""
    if not isinstance(tree, dict) or not tree:
        return {prefix: tree}
    out: dict[str, Any] = {}
    for key, value in tree.items():
        out.update(flat(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def may_change(key: str) -> bool:
    return any(key == allowed or key.startswith(allowed + ".") for allowed in RESUME_MAY_CHANGE)


def config_differences(stored: dict, requested: dict) -> list[str]:
    """'key: stored -> requested' for every key outside RESUME_MAY_CHANGE whose value differs."""
    old, new = flat(stored), flat(requested)
    absent = "(absent)"
    for key, value in ADDED_KEYS.items():  # a checkpoint from before the key: as if stored at its old value
        if key not in old and key in new and new[key] == value:
            old[key] = value
    return [f"{key}: {old.get(key, absent)} → {new.get(key, absent)}" for key in sorted(old.keys() | new.keys())
            if not may_change(key) and old.get(key, absent) != new.get(key, absent)]


def checked_resume(cfg: DictConfig) -> None:
    """Refuse `ckpt=` when the requested config differs from the checkpoint's outside RESUME_MAY_CHANGE."""
    path = cfg.ckpt
    if cfg.get("init_from"):
        raise ConfigError(f"ckpt={path} and init_from={cfg.init_from} were both given: ckpt= continues a run "
                          f"exactly, init_from= starts a new one from its weights. Pass one of them.")
    stored = ckpt_io.load(path).get("config")
    if not stored:
        raise ConfigError(f"checkpoint {path} holds no config, so it cannot be resumed exactly; start a new run "
                          f"from its weights with init_from={path} instead of ckpt=.")
    requested = OmegaConf.to_container(cfg, resolve=True)
    differences = config_differences(OmegaConf.to_container(OmegaConf.create(stored)), requested)
    if differences:
        lines = "\n  ".join(differences)
        raise ConfigError(
            f"ckpt={path} resumes only with the config it was trained with, and these keys differ (stored → "
            f"requested):\n  {lines}\nDrop those overrides to resume exactly (the stored config is in the "
            f"checkpoint and in the run's .hydra/config.yaml), or start a new run from these weights with "
            f"init_from={path} instead of ckpt=. A resume may change only: {', '.join(RESUME_MAY_CHANGE)}.")


def init_from(task, path: str | Path, fresh: tuple[str, ...] = ()) -> dict:
    """Load the network weights of checkpoint `path` into `task` (keys under the `fresh` prefixes keep their new
    values) and return the record of where they came from (`write_source` puts it in the run dir)."""
    path = Path(path)
    state = ckpt_io.load(path)
    ckpt_io.load_task_state(task, state, path, fresh=fresh,
                            hint="init_from= needs the same network (model.*) as the checkpoint it starts from.")
    best = state.get("best_metric")
    record = {"path": str(path.resolve()), "sha256": sha256(path), "epoch": state.get("epoch"),
              "global_step": state.get("global_step"), "monitor": state.get("monitor"),
              "best_metric": best if best is not None and math.isfinite(best) else None}
    return record


def write_source(run_dir: Path, record: dict) -> None:
    """run_dir/init_from.json: where an init_from= run's weights came from."""
    (run_dir / "init_from.json").write_text(json.dumps(record, indent=2) + "\n")


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
