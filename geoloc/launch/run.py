"""What train.py and evaluate.py call: find the task through the registry and hand it the composed config.

Tests call these functions directly with a config from `hydra.compose`.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

import geoloc.tasks  # noqa: F401  (declares the task kind: every package under geoloc/tasks/ is a task)
from geoloc import registry
from geoloc.config import ConfigError
from geoloc.engine import distributed as dist
from geoloc.launch import resume
from geoloc.launch.run_log import run_log
from geoloc.launch.rundir import claimed

RUN_METRICS = "metrics.json"  # an evaluation's metrics in its own run dir
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
        given = command_line(cfg)
        cfg = without_hydra(cfg)
        with claimed(cfg.run_dir, ckpt=cfg.get("ckpt")) as run_dir, run_log(run_dir, "train"):
            canonical = getattr(task, "canonical_config", None)  # a task that can resume says how it compares
            if cfg.get("ckpt") and canonical is not None:  # before any data is generated or checked
                cfg = resume.resumed_config(cfg, task.RESUME_MAY_CHANGE, canonical, given)
            return task.train(cfg, run_dir)
    finally:
        dist.cleanup()


def objective(cfg: DictConfig, best: dict) -> float:
    """The value a Hydra sweeper optimises for a run of `cfg` that returned `best`: the metric the task names with
    `sweep_metric(cfg)` (the cross-view task: the one that selected best.pt; MMDIP: the fused R@1), R@1 for a task
    that names none. NaN where the run did not report it (a rank > 0 of MMDIP), never a made-up 0."""
    task = find_task(cfg.get("task"))
    key = task.sweep_metric(cfg) if callable(getattr(task, "sweep_metric", None)) else "R@1"
    value = best.get(key)
    return float(value) if isinstance(value, (int, float)) else float("nan")


def command_line(cfg: DictConfig) -> list[str] | None:
    """The overrides the command line gave, as Hydra recorded them (None for a config composed in code without
    its Hydra node)."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return list(HydraConfig.get().overrides.task)
    if "hydra" in cfg:  # hydra.compose(..., return_hydra_config=True)
        return list(cfg.hydra.overrides.task)
    return None


def without_hydra(cfg: DictConfig) -> DictConfig:
    """`cfg` without Hydra's own node, which only a config composed with return_hydra_config holds."""
    if "hydra" not in cfg:
        return cfg
    from omegaconf import OmegaConf, open_dict

    plain = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    with open_dict(plain):
        del plain["hydra"]
    return plain


def evaluate(cfg: DictConfig) -> dict:
    """Score cfg.ckpt with the task that wrote it. Under Hydra its run dir is owned like a training's, so a failed
    start leaves none, and holds the evaluation's record: `.hydra/`, `evaluate.log` (what it printed) and
    `metrics.json` (besides any metrics_out=). A config composed outside Hydra may have no run dir."""
    from geoloc.engine import checkpoint

    run_dir = OmegaConf.select(cfg, "run_dir", throw_on_resolution_failure=False)
    try:
        with claimed(run_dir, role="evaluation") if run_dir else contextlib.nullcontext(), run_log(run_dir, "evaluate"):
            refuse_existing_metrics_out(cfg)
            state = checkpoint.load(cfg.ckpt)
            stored = OmegaConf.create(state.get("config") or "{}")
            metrics = find_task(stored.get("task")).evaluate(cfg, state)
            if cfg.get("metrics_out") and dist.is_main():
                write_metrics(Path(cfg.metrics_out), metrics, overwrite=cfg.get("metrics_out_overwrite", False))
            if run_dir and dist.is_main():
                write_metrics(Path(run_dir) / RUN_METRICS, metrics, overwrite=True)
            return metrics
    finally:  # a torchrun launch leaves its process group before exit, as train() does: a rank that exits with it
        dist.cleanup()  # alive can abort in the group's threads ("terminate called without an active exception")


def refuse_existing_metrics_out(cfg: DictConfig) -> None:
    """metrics_out= never replaces a file silently; checked before the evaluation (and again as it is written)."""
    out = cfg.get("metrics_out")
    if out and Path(out).exists() and not cfg.get("metrics_out_overwrite", False):
        raise ConfigError(f"metrics_out={out} already exists; nothing was evaluated. Choose another file, or pass "
                          f"metrics_out_overwrite=true to replace it.")


def write_metrics(out: Path, metrics: dict, overwrite: bool) -> None:
    """The metrics as JSON in `out`, whole or not at all: written to a temp file beside it, then linked into place,
    which fails if `out` appeared in the meantime (another evaluation with the same metrics_out) unless
    `overwrite`, so no result is lost in silence."""
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(metrics, indent=2) + "\n")
        if overwrite:
            os.replace(tmp, out)
            return
        try:
            os.link(tmp, out)
        except FileExistsError:
            raise ConfigError(f"metrics_out={out} was created by someone else while this evaluation ran; its "
                              f"result is kept and this one is in nothing. Run again with another metrics_out, or "
                              f"metrics_out_overwrite=true. These metrics: {json.dumps(metrics)}") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
