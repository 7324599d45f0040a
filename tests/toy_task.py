"""The smallest Task and dataset the Trainer runs: for tests of what fit() writes, not of any method."""

from __future__ import annotations

import torch
from geoloc.engine import Task
from geoloc.engine.sampling import split_key


class Points(torch.utils.data.Dataset):
    """{"x": [i]} for i in 0..n-1."""

    def __init__(self, n: int = 4):
        self.n = n

    def __len__(self):
        return self.n

    def __getitem__(self, key):  # the trainer's sampler yields (index, epoch) keys
        return {"x": torch.tensor([float(split_key(key)[0])])}


class ScriptedRecall(Task):
    """Fits one weight to the points; each validation reports the next R@1 of `script`, so the log is known."""

    monitor = "R@1"

    def __init__(self, script=()):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(1))
        self.script = list(script)

    def configure_optimizers(self):
        return [torch.optim.SGD(self.parameters(), lr=0.1)], []

    def training_step(self, batch, engine):
        return {"loss": ((self.weight - batch["x"]) ** 2).mean()}

    def validation_step(self, batch):
        return {"x": batch["x"]}

    def validation_epoch_end(self, outputs):
        return {"R@1": self.script.pop(0)}
