"""Run logging: TensorBoard scalars/images/embeddings and a metrics.jsonl, written by rank 0 only."""

from __future__ import annotations

import json
import os
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
        self._purge_step: int | None = None
        if self.enabled:
            self.run_dir.mkdir(parents=True, exist_ok=True)

    @property
    def tb(self):
        if self._tb is None and self.enabled:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(log_dir=str(self.run_dir / "tb"), purge_step=self._purge_step)
        return self._tb

    def resume_at(self, step: int) -> None:
        """Continue a run from its checkpoint at `step`: drop the metrics.jsonl rows a killed run wrote after it
        (and a half-written last line), and have TensorBoard hide its events after it (purge_step), so the logs
        read as one uninterrupted run."""
        if not self.enabled:
            return
        self._purge_step = step + 1
        path = self.run_dir / "metrics.jsonl"
        if not path.is_file():
            return
        kept = []
        for line in path.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            if row.get("step", 0) <= step:
                kept.append(line + "\n")
        tmp = path.with_name(".metrics.jsonl.tmp")
        tmp.write_text("".join(kept))
        os.replace(tmp, path)

    def holds(self, key: str) -> bool:
        """Whether metrics.jsonl already has a row with `key` (e.g. a run resumed in its own folder)."""
        path = self.run_dir / "metrics.jsonl"
        if not self.enabled or not path.is_file():
            return False
        for line in path.read_text().splitlines():
            try:
                if key in json.loads(line):
                    return True
            except json.JSONDecodeError:
                continue
        return False

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
