"""The hand-written trainer: epochs, AMP, accumulation, clipping, validation, checkpoints, logging, DDP.

Shaped like a minimal Lightning Fabric loop (see docs/architecture.md for the Task contract):

    trainer = Trainer(cfg.trainer, run_dir, config_yaml)
    best = trainer.fit(task, train_set, val_set, batch_size=64)

Its config is trainer_config.py's TrainerConfig; what a task's step sees of it is step_engine.py's Engine.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

import geoloc
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine import distributed as dist
from geoloc.engine.device import amp_dtype, autocast, log_cpu_precision, on_for_cuda
from geoloc.engine.env import record_environment
from geoloc.engine.logging import RunLogger
from geoloc.engine.sampling import EpochSampler
from geoloc.engine.step_engine import Engine
from geoloc.engine.task import Task
from geoloc.engine.trainer_config import TrainerConfig


class NonFiniteLossError(RuntimeError):
    """Raised when a loss is NaN or inf; the last good checkpoint is left untouched."""


class Trainer:
    def __init__(self, cfg: TrainerConfig, run_dir: str | Path, config_yaml: str = ""):
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.config_yaml = config_yaml
        self.device = dist.init_from_env(cfg.device)
        self.amp_dtype = amp_dtype(cfg.precision, self.device, cfg.cpu_precision)
        log_cpu_precision(self.device, cfg.cpu_precision, str(self.run_dir))
        # trainer.channels_last / trainer.compile resolved for this device ("auto": on for CUDA only)
        self.channels_last = on_for_cuda(cfg.channels_last, self.device)
        self.compile = on_for_cuda(cfg.compile, self.device)
        # GradScaler only matters for fp16; disabled it is a transparent pass-through (one code path).
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=self.amp_dtype == torch.float16)
        self.logger = RunLogger(self.run_dir)
        self.epoch = 0
        self.global_step = 0
        self.sign = 1.0 if cfg.monitor_mode == "max" else -1.0  # best = the largest sign * metric
        self.best_metric = -math.inf  # sign * the best monitored value so far
        self.best: dict[str, float] = {}
        self.init_from: dict | None = None  # where the weights of an init_from= run came from (resume.init_from)
        self.engine = Engine(self)
        self.writer = ckpt_io.CheckpointWriter()  # last.pt and best.pt, written while the next epoch trains

    # ---- helpers -------------------------------------------------------------------------------------------
    def autocast(self):
        return autocast(self.cfg.precision, self.device, self.cfg.cpu_precision)

    def check_finite(self, loss: torch.Tensor) -> None:
        if not torch.isfinite(loss.detach()).all():
            raise NonFiniteLossError(
                f"loss is {loss.item()} at epoch {self.epoch}, step {self.global_step}. The run stopped; the last "
                f"good checkpoint is {self.run_dir / 'last.pt'} (if an epoch finished). Lower optim.lr, enable "
                f"trainer.grad_clip, or use trainer.precision=32."
            )

    def loader(self, dataset: Dataset, batch_size: int, train: bool, batch_sampler=None) -> DataLoader:
        """Seeded EpochSampler batches, or the task's `batch_sampler` (geoloc/data/samplers.py) when given."""
        if batch_size < 1:
            raise ValueError(f"batch size must be >= 1, got {batch_size}")
        workers = self.cfg.num_workers
        common = dict(num_workers=workers, pin_memory=self.cfg.pin_memory and self.device.type == "cuda",
                      persistent_workers=self.cfg.persistent_workers and workers > 0)
        if batch_sampler is not None:
            return DataLoader(dataset, batch_sampler=batch_sampler, **common)
        sampler = EpochSampler(len(dataset), shuffle=train, seed=self.cfg.seed,
                               rank=dist.rank(), world_size=dist.world_size())
        return DataLoader(dataset, batch_size=batch_size, sampler=sampler,
                          drop_last=train and len(sampler) >= 2 * batch_size, **common)

    def _to_device(self, batch: dict, task: Task) -> dict:
        """Move, then the task's hook (which may turn uint8 images into float ones), then channels_last: it
        applies to floating-point 4-D tensors only, so a hook running after it would leave them contiguous."""
        moved = {k: v.to(self.device, non_blocking=True) if isinstance(v, torch.Tensor) else v
                 for k, v in batch.items()}
        out = task.on_after_batch_transfer(moved)
        if self.channels_last:
            out = {k: v.contiguous(memory_format=torch.channels_last)
                   if isinstance(v, torch.Tensor) and v.ndim == 4 and v.is_floating_point() else v
                   for k, v in out.items()}
        return out

    # ---- checkpoints ---------------------------------------------------------------------------------------
    def _state(self, task: Task, optimizers, schedulers) -> dict[str, Any]:
        return {
            "task": task.state_dict(),
            "optimizers": [o.state_dict() for o in optimizers],
            "schedulers": [s.state_dict() for s in schedulers],
            "scaler": self.scaler.state_dict(),
            "epoch": self.epoch,
            "global_step": self.global_step,
            "best_metric": self.best_metric,
            "best": self.best,
            "monitor": self.monitor(task),
            "monitor_mode": self.cfg.monitor_mode,
            "config": self.config_yaml,
            "task_info": task.checkpoint_info(),
            "init_from": self.init_from,
            "rng": ckpt_io.rng_state(),
            "geoloc_version": geoloc.__version__,
            "environment": self.environment,  # versions and thread count: what makes the figures reproducible
        }

    def _restore(self, path: Path, task: Task, optimizers, schedulers) -> None:
        state = ckpt_io.load(path, map_location=self.device)
        ckpt_io.load_task_state(task, state, path, hint="Resume with the config it was trained with.")
        for o, s in zip(optimizers, state["optimizers"]):
            o.load_state_dict(s)
        for sch, s in zip(schedulers, state["schedulers"]):
            sch.load_state_dict(s)
        self.scaler.load_state_dict(state["scaler"])
        self.epoch = state["epoch"] + 1
        self.global_step = state["global_step"]
        self.best_metric = state["best_metric"]
        self.best = dict(state.get("best", {}))
        self.init_from = state.get("init_from")
        ckpt_io.set_rng_state(state["rng"])
        self.logger.resume_at(self.global_step)  # the killed run's rows after the checkpoint are run again

    # ---- the loop ------------------------------------------------------------------------------------------
    def fit(self, task: Task, train_set: Dataset, val_set: Dataset | None, batch_size: int,
            val_batch_size: int | None = None, resume: str | Path | None = None) -> dict[str, float]:
        """Train `task`; return the metrics of the best validation (or of the last epoch without validation)."""
        self.environment = record_environment(self.run_dir)
        task.to(self.device)
        if self.channels_last:
            task.to(memory_format=torch.channels_last)
        optimizers, schedulers = task.configure_optimizers()
        if resume:
            self._restore(Path(resume), task, optimizers, schedulers)
        model: torch.nn.Module = task
        if dist.is_dist():
            if not task.automatic_optimization:
                raise NotImplementedError("DDP runs need automatic_optimization; run this task on one process.")
            model = torch.nn.parallel.DistributedDataParallel(
                task, device_ids=[self.device.index] if self.device.type == "cuda" else None,
                broadcast_buffers=False)
        self.model = self._compiled(model, task) if self.compile else model
        self._eager_model, self._compile_unproven = model, self.compile
        train_loader = task.train_dataloader(train_set, batch_size, self.engine)
        val_loader = task.val_dataloaders(val_set, val_batch_size or batch_size, self.engine) if val_set else None
        monitor = self.monitor(task)
        # what selects best.pt, in the log beside the numbers, so a table over runs picks best epochs the same way
        if not self.logger.holds("run/monitor"):  # once per log: a resume in place keeps the run's first row
            self.logger.log({"monitor": monitor, "monitor_mode": self.cfg.monitor_mode}, self.global_step,
                            prefix="run/")

        last_val: dict[str, float] = {}
        try:
            for epoch in range(self.epoch, self.cfg.max_epochs):
                self.epoch = epoch
                task.on_train_epoch_start(self.engine)
                for sampler in (train_loader.sampler, train_loader.batch_sampler):
                    if hasattr(sampler, "set_epoch"):
                        sampler.set_epoch(epoch)
                train_logs = self._train_epoch(task, train_loader, optimizers)
                for s in schedulers:
                    s.step()
                validate = val_loader is not None and (
                    (epoch + 1) % self.cfg.val_every_n_epochs == 0 or epoch + 1 == self.cfg.max_epochs)
                if validate:
                    last_val = self.validate(task, val_loader)
                    self.logger.log(last_val, self.global_step, prefix="val/")
                    self._print_metrics(epoch, last_val)
                if validate and monitor not in last_val:
                    raise KeyError(f"trainer.monitor={monitor!r} is not among the validation metrics {list(last_val)}")
                improved = validate and self.sign * last_val[monitor] > self.best_metric
                if improved:
                    self.best_metric = self.sign * last_val[monitor]
                    self.best = {**last_val, "epoch": epoch}
                self.logger.log({**train_logs, "epoch": epoch}, self.global_step, prefix="train/epoch_")
                if dist.is_main():  # serialised once, while the next epoch trains; best.pt links to last.pt
                    best_due = improved or (val_loader is None and epoch + 1 == self.cfg.max_epochs)
                    self.writer.submit(self._state(task, optimizers, schedulers), self.run_dir / "last.pt",
                                       also=(self.run_dir / "best.pt",) if best_due else ())
                dist.barrier()
        finally:
            self.writer.join()  # the last epoch's checkpoint is on disk before fit returns or raises
            # the DDP wrapper holds the process group: dropped here, so dist.cleanup() can free the group's
            # threads while the interpreter is alive (not at its finalisation, where gloo aborts the process)
            self.model = self._eager_model = None
        self.logger.close()
        return self.best or last_val

    def _compiled(self, model: torch.nn.Module, task: Task) -> torch.nn.Module:
        """torch.compile of what the step calls: the task (or its DDP wrapper); a task that steps its own optimizers
        (automatic_optimization=False) has its networks compiled in place instead, since its step runs backward
        and the optimizers' steps, which a compiled graph would break around."""
        if task.automatic_optimization:
            return torch.compile(model)
        for network in task.children():
            network.compile()
        return model

    def _eager(self, task: Task, err: Exception) -> None:
        """The first compiled step failed: go on eagerly, with one line saying why."""
        first = next((line.strip() for line in str(err).splitlines() if line.strip()), "")
        tqdm.write(f"trainer.compile: torch.compile failed on the first step ({type(err).__name__}: {first[:200]}); "
                   "training goes on eagerly. Set trainer.compile=false to skip the attempt.")
        for network in task.children():
            network._compiled_call_impl = None  # undo Module.compile() (the in-place compile of _compiled)
        self.model, self._compile_unproven = self._eager_model, False

    def _step(self, task: Task, batch: dict, optimizers, i: int, n_batches: int) -> dict:
        """One training step of the model; the first compiled one falls back to eager if compiling fails."""
        if not self._compile_unproven:
            return self._run_step(task, batch, optimizers, i, n_batches)
        try:
            out = self._run_step(task, batch, optimizers, i, n_batches)
        except Exception as err:  # noqa: BLE001 - any failure of a compiled first step is retried eagerly
            self._eager(task, err)
            for optimizer in optimizers:
                optimizer.zero_grad(set_to_none=True)
            out = self._run_step(task, batch, optimizers, i, n_batches)  # an eager failure is the real error
        self._compile_unproven = False
        return out

    def _run_step(self, task: Task, batch: dict, optimizers, i: int, n_batches: int) -> dict:
        if not task.automatic_optimization:
            return self.model(batch, self.engine)
        with self.autocast():
            out = self.model(batch, self.engine)
        self.engine.backward(out["loss"] / self.cfg.accumulate)
        if (i + 1) % self.cfg.accumulate == 0 or i + 1 == n_batches:
            self.engine.step(optimizers[0])
        return out

    def _train_epoch(self, task: Task, loader: DataLoader, optimizers) -> dict[str, float]:
        self.model.train()
        n_batches = len(loader)
        if self.cfg.limit_train_batches:
            n_batches = min(n_batches, self.cfg.limit_train_batches)
        bar = tqdm(total=n_batches, desc=f"epoch {self.epoch}", disable=not (self.cfg.progress and dist.is_main()),
                   dynamic_ncols=True, leave=False)
        total, count, t0, samples = 0.0, 0, time.perf_counter(), 0
        for i, batch in enumerate(loader):
            if i >= n_batches:
                break
            batch = self._to_device(batch, task)
            out = self._step(task, batch, optimizers, i, n_batches)
            loss = out["loss"]
            task.on_train_batch_end(out)
            self.global_step += 1
            total += float(loss.detach())
            count += 1
            samples += next(iter(v for v in batch.values() if isinstance(v, torch.Tensor))).shape[0]
            speed = samples * dist.world_size() / (time.perf_counter() - t0)
            bar.set_postfix(loss=f"{total / count:.4f}", samples_s=f"{speed:.1f}")
            bar.update(1)
            if self.global_step % self.cfg.log_every_n_steps == 0:
                logs = {k: v for k, v in out.items() if k != "loss" and _is_scalar(v)}
                logs["loss"] = float(loss.detach())
                logs["lr"] = optimizers[0].param_groups[0]["lr"]
                self.logger.log(logs, self.global_step, prefix="train/")
        bar.close()
        return {"loss": dist.reduce_mean(total / max(count, 1), self.device),
                "samples_per_s": samples * dist.world_size() / (time.perf_counter() - t0)}

    def monitor(self, task: Task) -> str:
        monitor = self.cfg.monitor or task.monitor
        if not monitor:
            raise ValueError(f"{type(task).__name__} names no validation metric to select best.pt by: set its "
                             f"`monitor` attribute, or trainer.monitor=<a key its validation returns>")
        return monitor

    @torch.no_grad()
    def validate(self, task: Task, loaders: DataLoader | dict[str, DataLoader]) -> dict[str, float]:
        """Run validation_step over each (sharded) loader, gather in dataset order, then validation_epoch_end.

        One loader: validation_epoch_end gets its outputs {key: tensor}. Several (a dict from the task's
        val_dataloaders): it gets {loader name: {key: tensor}}, and validation_step is told the loader's name."""
        task.eval()
        named = loaders if isinstance(loaders, dict) else {"val": loaders}
        outputs = {name: self._run_validation(task, loader, name if len(named) > 1 else None)
                   for name, loader in named.items()}
        metrics = task.validation_epoch_end(outputs if len(named) > 1 else next(iter(outputs.values())))
        task.train()
        return metrics

    @torch.no_grad()
    def validation_outputs(self, task: Task, loader: DataLoader, name: str) -> dict[str, torch.Tensor]:
        """validation_step's outputs over one named loader, gathered in dataset order: validate's first half, for
        a caller that scores several query sets against one encoding of the references (`geoloc bench`)."""
        task.eval()
        try:
            return self._run_validation(task, loader, name)
        finally:
            task.train()

    def _run_validation(self, task: Task, loader: DataLoader, name: str | None) -> dict[str, torch.Tensor]:
        chunks: dict[str, list[torch.Tensor]] = {}
        for batch in tqdm(loader, desc=f"validate {name or ''}".strip(), leave=False, dynamic_ncols=True,
                          disable=not (self.cfg.progress and dist.is_main())):
            batch = self._to_device(batch, task)
            with self.autocast():
                out = task.validation_step(batch) if name is None else task.validation_step(batch, name)
            for k, v in out.items():
                chunks.setdefault(k, []).append(v.float() if v.is_floating_point() else v)
        outputs = {k: dist.all_gather_variable(torch.cat(v)) for k, v in chunks.items()}
        if dist.is_dist():  # shards are strided over ranks: put the samples back in dataset order
            order = torch.argsort(outputs["index"])
            outputs = {k: v[order] for k, v in outputs.items()}
        return outputs

    def _print_metrics(self, epoch: int, metrics: dict[str, float]) -> None:
        if dist.is_main():
            # floats as figures; a string names what they were measured against (e.g. a label set)
            text = "  ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in metrics.items()
                             if isinstance(v, (float, str)))
            tqdm.write(f"[epoch {epoch}] {text}")


def _is_scalar(v: Any) -> bool:
    return isinstance(v, (int, float)) or (isinstance(v, torch.Tensor) and v.numel() == 1)
