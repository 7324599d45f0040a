"""What train.py and evaluate.py call: pick the task's runner and hand it the composed config.

Tests call these functions directly with a config from `hydra.compose`.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from geoloc.engine import distributed as dist


def run_dir(cfg: DictConfig) -> Path:
    path = Path(cfg.run_dir)
    if dist.is_main():
        path.mkdir(parents=True, exist_ok=True)
    return path


def train(cfg: DictConfig) -> dict:
    try:
        if cfg.task.name == "mmdip":
            from geoloc.tasks import mmdip

            return mmdip.train(cfg, run_dir(cfg))
        if cfg.task.name == "crossview":
            from geoloc.tasks import crossview_run

            return crossview_run.train(cfg, run_dir(cfg))
        raise ValueError(f"unknown task {cfg.task.name!r}; choose task=crossview or task=mmdip")
    finally:
        dist.cleanup()


def evaluate(cfg: DictConfig) -> dict:
    from omegaconf import OmegaConf

    from geoloc.engine import checkpoint

    state = checkpoint.load(cfg.ckpt)
    stored = OmegaConf.create(state.get("config") or "{}")
    if OmegaConf.select(stored, "task.name") == "mmdip":
        from geoloc.tasks import mmdip

        return mmdip.evaluate(cfg, cfg.ckpt, cfg.metrics_out)
    from geoloc.tasks import crossview_run

    return crossview_run.evaluate(cfg, state)
