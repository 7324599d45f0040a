"""The contract a method implements to run on the Trainer (a LightningModule in miniature).

A task owns its networks and buffers (so `state_dict()` is the whole learnable state, GMS queue included).
The Trainer owns everything else: devices, epochs, AMP, accumulation, clipping, checkpoints, logging and DDP.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn


class Task(nn.Module):
    #: the validation metric that selects best.pt when trainer.monitor is not set (trainer.monitor_mode: max/min);
    #: every task names its own
    monitor: str | None = None
    #: False for tasks with several optimizers that step themselves (GANs); they call engine.backward/step
    automatic_optimization: bool = True

    def configure_optimizers(self) -> tuple[list[torch.optim.Optimizer], list[Any]]:
        """Return (optimizers, schedulers). Schedulers are stepped once per epoch."""
        raise NotImplementedError

    def training_step(self, batch: dict[str, torch.Tensor], engine: Any) -> dict[str, Any]:
        """One step on one batch. Return {"loss": scalar tensor, **values to log}."""
        raise NotImplementedError

    def on_after_batch_transfer(self, batch: dict[str, Any]) -> dict[str, Any]:
        """The batch just moved to the device, before the Trainer makes its 4-D float tensors channels_last: the
        place for batched work on the device, e.g. normalising uint8 images that data workers returned (Lightning's
        hook of the same name). Runs on every batch the engine moves: training, validation, engine.to_device."""
        return batch

    def on_train_batch_end(self, outputs: dict[str, Any]) -> None:
        """Called after the optimizer step (e.g. to push to a queue)."""

    def on_train_epoch_start(self, engine: Any) -> None:
        """Called before each training epoch (e.g. to give a hard-sample sampler fresh descriptors)."""

    def train_dataloader(self, dataset, batch_size: int, engine: Any):
        """The training loader; override to bring a batch sampler (engine.loader(..., batch_sampler=...))."""
        return engine.loader(dataset, batch_size, train=True)

    def val_dataloaders(self, dataset, batch_size: int, engine: Any):
        """One DataLoader, or {name: DataLoader} when validation reads several sets (queries and a gallery)."""
        return engine.loader(dataset, batch_size, train=False)

    def validation_step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Per-sample outputs for one validation batch (first dim = batch)."""
        raise NotImplementedError

    def validation_epoch_end(self, outputs: dict[str, torch.Tensor]) -> dict[str, float]:
        """Metrics from all validation outputs, concatenated over batches and ranks in dataset order."""
        raise NotImplementedError

    def checkpoint_info(self) -> dict[str, Any]:
        """What a checkpoint records of the task beyond its weights and config, in plain types (strings, numbers,
        lists, dicts), e.g. the kind of query images the cross-view task trained on; stored as `task_info`."""
        return {}

    def forward(self, batch: dict[str, torch.Tensor], engine: Any) -> dict[str, Any]:
        # DDP only syncs gradients of what runs inside forward(), so the trainer calls the step through here.
        return self.training_step(batch, engine)
