"""A task plug-in: fit one number to the mean of 0..n-1 on geoloc's engine, and score a checkpoint of it.

A task is any object registered under `task.name` with train(cfg, run_dir) and evaluate(cfg, state); here a class
of two static methods. The Trainer writes run_dir/{best,last}.pt with the config, so evaluate.py finds this task
again through the checkpoint's task.name and task.module.
"""

from pathlib import Path

import torch
from geoloc.config import checked, to_yaml
from geoloc.engine import Task, Trainer, TrainerConfig
from geoloc.engine.sampling import split_key
from geoloc.registry import register
from omegaconf import OmegaConf


class Numbers(torch.utils.data.Dataset):
    def __init__(self, n: int):
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, key) -> dict:
        return {"x": torch.tensor([float(split_key(key)[0])])}


class FitMean(Task):
    monitor = "error"

    def __init__(self, lr: float = 0.0):
        super().__init__()
        self.mean, self.lr = torch.nn.Parameter(torch.zeros(1)), lr

    def configure_optimizers(self):
        return [torch.optim.SGD(self.parameters(), lr=self.lr)], []

    def training_step(self, batch, engine):
        return {"loss": ((self.mean - batch["x"]) ** 2).mean()}

    def validation_step(self, batch):
        return {"x": batch["x"]}

    def validation_epoch_end(self, outputs):
        return {"error": float((self.mean - outputs["x"].mean()).abs())}


@register("task", "fit_mean")
class FitMeanTask:
    @staticmethod
    def train(cfg, run_dir: Path) -> dict:
        trainer = Trainer(checked(cfg.trainer, TrainerConfig, "trainer"), run_dir, to_yaml(cfg))
        data = Numbers(cfg.task.n)
        return trainer.fit(FitMean(cfg.task.lr), data, data, batch_size=cfg.task.n)

    @staticmethod
    def evaluate(cfg, state: dict) -> dict:
        task = FitMean()
        task.load_state_dict(state["task"])
        n = OmegaConf.create(state["config"]).task.n  # the checkpoint's own config
        mean = task.mean.item()
        return {"mean": mean, "error": abs(mean - (n - 1) / 2)}  # the launcher writes them to metrics_out
