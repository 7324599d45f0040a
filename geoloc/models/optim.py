"""The registered optimizers. A factory takes the parameters to train and `max_epochs`, plus its config keys, and
returns (optimizer, scheduler or None); the scheduler is stepped once per epoch. This module declares the
`optimizer` kind (config section `optim`) and registers the built-ins.

adam: the paper's Adam (lr 1e-4, betas 0.9/0.999) with StepLR /10 every 80 epochs.
adamw: Sample4Geo's AdamW with linear warm-up then cosine decay to 0 over the run (there stepped per iteration;
here per epoch, which on a CPU-sized run of 15 epochs keeps the same shape).
"""

from __future__ import annotations

import math
from typing import Iterable

import torch

from geoloc.registry import declare, register

declare("optimizer", section="optim", runtime=("params", "max_epochs"))


@register("optimizer", "adam")
def adam(params: Iterable, max_epochs: int, lr: float = 1e-4, betas: tuple[float, float] = (0.9, 0.999),
         weight_decay: float = 0.0, step_size: int = 80, gamma: float = 0.1):
    _check(lr=lr, step_size=step_size)
    opt = torch.optim.Adam(params, lr=lr, betas=tuple(betas), weight_decay=weight_decay)
    return opt, torch.optim.lr_scheduler.StepLR(opt, step_size=step_size, gamma=gamma)


@register("optimizer", "adamw")
def adamw(params: Iterable, max_epochs: int, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
          weight_decay: float = 0.01, warmup_epochs: int = 1):
    _check(lr=lr, max_epochs=max_epochs)
    if warmup_epochs < 0:
        raise ValueError(f"optim.warmup_epochs must be >= 0, got {warmup_epochs}")
    opt = torch.optim.AdamW(params, lr=lr, betas=tuple(betas), weight_decay=weight_decay)
    return opt, torch.optim.lr_scheduler.LambdaLR(opt, warmup_cosine(warmup_epochs, max_epochs))


def warmup_cosine(warmup: int, total: int):
    """Epoch e -> lr factor: (e + 1) / (warmup + 1) during the warm-up, then a cosine from 1 to 0 at `total`."""

    def factor(epoch: int) -> float:
        if epoch < warmup:
            return (epoch + 1) / (warmup + 1)
        progress = (epoch - warmup) / max(1, total - warmup)
        return 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))

    return factor


def _check(**positive) -> None:
    for key, value in positive.items():
        if value <= 0:
            raise ValueError(f"optim.{key} must be > 0, got {value}")
