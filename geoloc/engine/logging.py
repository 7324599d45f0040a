"""Run logging: TensorBoard scalars/images/embeddings and a metrics.jsonl, written by rank 0 only."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from geoloc.engine import distributed as dist


class RunLogger:
    def __init__(self, run_dir: str | Path, enabled: bool | None = None):
        self.run_dir = Path(run_dir)
        self.enabled = dist.is_main() if enabled is None else enabled
        self._tb = None
        if self.enabled:
            self.run_dir.mkdir(parents=True, exist_ok=True)

    @property
    def tb(self):
        if self._tb is None and self.enabled:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(log_dir=str(self.run_dir / "tb"))
        return self._tb

    def log(self, metrics: dict[str, Any], step: int, prefix: str = "") -> None:
        """Scalars to TensorBoard and one JSON line to metrics.jsonl."""
        if not self.enabled:
            return
        clean = {f"{prefix}{k}": _as_float(v) for k, v in metrics.items()}
        for k, v in clean.items():
            if isinstance(v, float):
                self.tb.add_scalar(k, v, step)
        with open(self.run_dir / "metrics.jsonl", "a") as f:
            f.write(json.dumps({"step": step, "time": time.time(), **clean}) + "\n")

    def image(self, tag: str, image_hwc: np.ndarray, step: int) -> None:
        if self.enabled:
            self.tb.add_image(tag, image_hwc, step, dataformats="HWC")

    def embedding(self, tag: str, vectors: torch.Tensor, labels: list, step: int, images=None) -> None:
        if self.enabled:
            self.tb.add_embedding(vectors, metadata=labels, label_img=images, global_step=step, tag=tag)

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()


def _as_float(v: Any) -> Any:
    if isinstance(v, torch.Tensor) and v.numel() == 1:
        return float(v.detach().cpu())
    if isinstance(v, (np.floating, np.integer)):
        return float(v)
    return v
