"""A run killed mid-training, as a KeyboardInterrupt raised when a chosen global step starts."""

from __future__ import annotations

from typing import Callable

import pytest


def run_killed_at(task_class: type, step: int, run: Callable[[], object], monkeypatch) -> None:
    """run(), killed as global step `step` starts in `task_class.training_step` (restored afterwards)."""
    original = task_class.training_step

    def dying(self, batch, engine):
        if engine.global_step == step:
            raise KeyboardInterrupt("simulated kill")
        return original(self, batch, engine)

    monkeypatch.setattr(task_class, "training_step", dying)
    with pytest.raises(KeyboardInterrupt):
        run()
    monkeypatch.setattr(task_class, "training_step", original)
