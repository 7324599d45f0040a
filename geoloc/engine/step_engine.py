"""What a task sees of the trainer during a step (`Engine`): the device, the epoch, one AMP context, backward and
step. The trainer owns the state; the task calls only these."""

from __future__ import annotations

import torch
from torch.utils.data import DataLoader

from geoloc.engine.task import Task


class Engine:
    """What a task sees of the trainer during a step: one AMP context, backward and step."""

    def __init__(self, trainer):
        self._t = trainer  # the Trainer (trainer.py) whose state it shows; not imported here, which imports this

    @property
    def device(self) -> torch.device:
        return self._t.device

    @property
    def epoch(self) -> int:
        return self._t.epoch

    @property
    def global_step(self) -> int:
        return self._t.global_step

    @property
    def seed(self) -> int:
        return self._t.cfg.seed

    def loader(self, dataset, batch_size: int, train: bool, batch_sampler=None) -> DataLoader:
        """A DataLoader as the trainer builds them (seeded, DDP-sharded, workers from trainer config)."""
        return self._t.loader(dataset, batch_size, train, batch_sampler)

    def to_device(self, batch: dict, task: Task) -> dict:
        """`batch` on the device as the trainer moves it: `task.on_after_batch_transfer`, then channels_last."""
        return self._t._to_device(batch, task)

    def autocast(self):
        return self._t.autocast()

    def backward(self, loss: torch.Tensor) -> None:
        self._t.check_finite(loss)
        self._t.scaler.scale(loss).backward()

    def step(self, optimizer: torch.optim.Optimizer) -> None:
        """Unscale, clip, step and zero one optimizer."""
        t = self._t
        if t.cfg.grad_clip > 0:
            t.scaler.unscale_(optimizer)
            params = [p for group in optimizer.param_groups for p in group["params"]]
            torch.nn.utils.clip_grad_norm_(params, t.cfg.grad_clip)
        t.scaler.step(optimizer)
        t.scaler.update()
        optimizer.zero_grad(set_to_none=True)
