"""Task.on_after_batch_transfer: the engine runs it on every batch it moves, after the move and before it makes
4-D float tensors channels_last, so a task that turns uint8 images into float ones keeps channels_last."""

from __future__ import annotations

import torch
from geoloc.engine import Task, Trainer, TrainerConfig
from geoloc.engine.sampling import split_key


class Pictures(torch.utils.data.Dataset):
    """{"image": 3×4×5 uint8, "index": i}, as the cross-view data workers return images."""

    def __len__(self):
        return 4

    def __getitem__(self, key):
        index, _ = split_key(key)
        return {"image": torch.full((3, 4, 5), index, dtype=torch.uint8), "index": index}


class Scaled(Task):
    """Scales uint8 images to float in its hook; records what its steps see."""

    monitor = "mean"

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.ones(1))
        self.seen: list[tuple[str, torch.Tensor]] = []

    def on_after_batch_transfer(self, batch):
        assert batch["image"].device.type == "cpu" and batch["image"].dtype == torch.uint8  # moved, not yet float
        return {**batch, "image": batch["image"].float() / 255}

    def configure_optimizers(self):
        return [torch.optim.SGD(self.parameters(), lr=0.1)], []

    def training_step(self, batch, engine):
        self.seen.append(("train", batch["image"]))
        return {"loss": (self.weight * batch["image"]).mean()}

    def validation_step(self, batch):
        self.seen.append(("val", batch["image"]))
        return {"value": batch["image"].mean((1, 2, 3)), "index": batch["index"]}

    def validation_epoch_end(self, outputs):
        return {"mean": float(outputs["value"].mean())}


def test_the_hook_runs_before_channels_last_in_training_and_validation(tmp_path):
    task = Scaled()
    cfg = TrainerConfig(max_epochs=1, num_workers=0, device="cpu", progress=False, persistent_workers=False,
                        channels_last=True)
    Trainer(cfg, tmp_path).fit(task, Pictures(), Pictures(), batch_size=2)
    assert [where for where, _ in task.seen] == ["train", "train", "val", "val"]
    for _, image in task.seen:
        assert image.dtype == torch.float32 and image.shape == (2, 3, 4, 5)
        assert image.is_contiguous(memory_format=torch.channels_last) and not image.is_contiguous()


def test_engine_to_device_runs_the_hook(tmp_path):
    trainer = Trainer(TrainerConfig(device="cpu", channels_last=True), tmp_path)
    batch = trainer.engine.to_device({"image": torch.zeros(2, 3, 4, 5, dtype=torch.uint8), "index": [0, 1]},
                                     Scaled())
    assert batch["image"].dtype == torch.float32
    assert batch["image"].is_contiguous(memory_format=torch.channels_last)
    assert batch["index"] == [0, 1]
