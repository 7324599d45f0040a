"""What `trainer:` in the config holds (TrainerConfig, checked on construction), and the one seeding call."""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from geoloc.engine.device import AUTO, check_device_name


@dataclass
class TrainerConfig:
    max_epochs: int = 100
    val_every_n_epochs: int = 1
    precision: str = "32"  # "32" | "bf16" | "16": the autocast on CUDA
    cpu_precision: str = "32"  # "32" | "bf16" | "auto" (bf16 where the CPU has it natively): the autocast on the CPU
    grad_clip: float = 0.0  # max global grad norm; 0 = off
    accumulate: int = 1
    num_workers: int = 4
    pin_memory: bool = True
    persistent_workers: bool = True
    device: str = "auto"  # "auto" | "cpu" | "cuda" | "cuda:N" (one rule with the apps: engine/device.py)
    seed: int = 0
    log_every_n_steps: int = 10
    limit_train_batches: int = 0  # 0 = all
    # GPU-first switches: "auto" is on for CUDA and off on the CPU (where they would change the figures or cost
    # more than they give); true/false as given. A compile that fails falls back to eager with one line.
    channels_last: Any = "auto"  # true | false | auto
    compile: Any = "auto"  # true | false | auto
    progress: bool = True
    monitor: str | None = None  # the validation metric that selects best.pt; null = the task's default
    monitor_mode: str = "max"  # max | min

    def __post_init__(self):
        if self.max_epochs < 1:
            raise ValueError(f"trainer.max_epochs must be >= 1, got {self.max_epochs}")
        if self.val_every_n_epochs < 1:
            raise ValueError(f"trainer.val_every_n_epochs must be >= 1, got {self.val_every_n_epochs}")
        if self.precision not in ("32", "bf16", "16"):
            raise ValueError(f"trainer.precision must be one of '32', 'bf16', '16', got {self.precision!r}")
        if self.cpu_precision not in ("32", "bf16", AUTO):
            raise ValueError(f"trainer.cpu_precision must be '32', 'bf16' or 'auto', got {self.cpu_precision!r}")
        if self.accumulate < 1:
            raise ValueError(f"trainer.accumulate must be >= 1, got {self.accumulate}")
        check_device_name(self.device, "trainer.device")
        for key in ("channels_last", "compile"):
            if getattr(self, key) not in (True, False, AUTO):
                raise ValueError(f"trainer.{key} must be true, false or auto, got {getattr(self, key)!r}")
        if self.monitor_mode not in ("max", "min"):
            raise ValueError(f"trainer.monitor_mode must be 'max' or 'min', got {self.monitor_mode!r}")


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch; call before building the task so weight init is reproducible."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
