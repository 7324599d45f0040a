"""Small cross-view training runs the end-to-end and resume tests share."""

from __future__ import annotations

import json

import pytest
from geoloc.launch import run
from geoloc.tasks.crossview.task import CrossViewTask

from conftest import TINY, compose_train


def train_cfg(root, run_dir, *extra):
    return compose_train([*TINY, f"dataset.root={root}", f"run_dir={run_dir}", *extra])


def val_records(run_dir):
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [json.loads(x) for x in lines if '"val/R@1"' in x]


def train_until_killed(cfg, monkeypatch, global_step: int) -> None:
    """run.train(cfg), killed (KeyboardInterrupt) as the step after `global_step` starts."""
    original = CrossViewTask.training_step

    def dying_step(self, batch, engine):
        if engine.global_step == global_step:
            raise KeyboardInterrupt("simulated kill")
        return original(self, batch, engine)

    monkeypatch.setattr(CrossViewTask, "training_step", dying_step)
    with pytest.raises(KeyboardInterrupt):
        run.train(cfg)
    monkeypatch.setattr(CrossViewTask, "training_step", original)
