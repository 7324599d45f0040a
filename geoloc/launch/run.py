"""What train.py and evaluate.py call: find the task through the registry and hand it the composed config.

Tests call these functions directly with a config from `hydra.compose`.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

import geoloc.tasks  # noqa: F401  (declares the task kind: every package under geoloc/tasks/ is a task)
from geoloc import registry
from geoloc.config import ConfigError
from geoloc.engine import distributed as dist
from geoloc.launch.rundir import claimed

DEFAULT_TASK = {"name": "crossview"}  # a checkpoint whose config names no task was written by the cross-view task


def find_task(section: DictConfig | dict | None):
    """The registered task that `section` (a config's `task`) names: an object with `train(cfg, run_dir)` and
    `evaluate(cfg, state)`; `task.module` is imported first, for a task from outside geoloc."""
    section = section if section is not None and section.get("name") else DEFAULT_TASK
    task = registry.find("task", section)
    missing = [entry for entry in ("train", "evaluate") if not callable(getattr(task, entry, None))]
    if missing:
        raise ConfigError(f"task {section['name']!r} ({task!r}) has no {' or '.join(missing)}(...); a task gives "
                          f"train(cfg, run_dir) and evaluate(cfg, state) (docs/extending.md)")
    return task


def train(cfg: DictConfig) -> dict:
    """Train in `cfg.run_dir`, which the run owns while it lasts (geoloc/launch/rundir.py)."""
    try:
        task = find_task(cfg.task)
        with claimed(cfg.run_dir, ckpt=cfg.get("ckpt")) as run_dir:
            return task.train(cfg, run_dir)
    finally:
        dist.cleanup()


def evaluate(cfg: DictConfig) -> dict:
    """Score cfg.ckpt with the task that wrote it. Under Hydra its run dir (Hydra's log and config) is owned like a
    training's, so a failed start leaves none; a config composed outside Hydra may have no run dir."""
    from geoloc.engine import checkpoint

    run_dir = OmegaConf.select(cfg, "run_dir", throw_on_resolution_failure=False)
    with claimed(run_dir, ckpt=cfg.ckpt) if run_dir else contextlib.nullcontext():
        refuse_existing_metrics_out(cfg)
        state = checkpoint.load(cfg.ckpt)
        stored = OmegaConf.create(state.get("config") or "{}")
        return find_task(stored.get("task")).evaluate(cfg, state)


def refuse_existing_metrics_out(cfg: DictConfig) -> None:
    """metrics_out= never replaces a file silently; checked before the evaluation, not after it."""
    out = cfg.get("metrics_out")
    if out and Path(out).exists() and not cfg.get("metrics_out_overwrite", False):
        raise ConfigError(f"metrics_out={out} already exists; nothing was evaluated. Choose another file, or pass "
                          f"metrics_out_overwrite=true to replace it.")
