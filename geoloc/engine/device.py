"""Which device a run or an app computes on: one rule for the trainer, evaluate.py and the apps."""

from __future__ import annotations

import contextlib
import re

import torch

AUTO = "auto"


def valid_devices() -> list[str]:
    """The device names this machine takes: auto, cpu, and cuda, cuda:0 .. cuda:N-1 where CUDA is available."""
    names = [AUTO, "cpu"]
    if torch.cuda.is_available():
        names += ["cuda", *(f"cuda:{i}" for i in range(torch.cuda.device_count()))]
    return names


def check_device_name(name: str, key: str) -> None:
    """A ValueError unless `name` is a device name geoloc takes anywhere: auto, cpu, cuda or cuda:N (whether this
    machine has it is resolve_device's question, asked when the run starts)."""
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", str(name).strip()):
        raise ValueError(f"{key} must be auto, cpu, cuda or cuda:N, got {name!r}")


def resolve_device(device: str | None = None) -> torch.device:
    """None or "auto": the GPU when CUDA is available, else the CPU; "cpu", "cuda", "cuda:N" as given. Anything
    else (another torch device type, a CUDA device this machine lacks) is a ValueError listing the valid names."""
    name = AUTO if device is None else str(device).strip()
    if name == AUTO:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        chosen = torch.device(name)
    except RuntimeError:
        chosen = None
    valid = ", ".join(valid_devices())
    if chosen is None or chosen.type not in ("cpu", "cuda"):
        raise ValueError(f"device={name!r} is not a device: use one of {valid}")
    if chosen.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={name!r} but CUDA is not available on this machine: use one of {valid}")
    if chosen.type == "cuda" and chosen.index is not None and chosen.index >= torch.cuda.device_count():
        raise ValueError(f"device={name!r} but this machine has {torch.cuda.device_count()} CUDA device(s): use "
                         f"one of {valid}")
    return chosen


def amp_dtype(precision: str, device: torch.device, cpu_precision: str = "32") -> torch.dtype | None:
    """The autocast dtype on `device`: trainer.precision ("32" | "bf16" | "16") on CUDA, trainer.cpu_precision
    ("32" | "bf16") on the CPU; None (no autocast) for "32". The CPU's is a key of its own, off by default, so a
    recipe that asks for bf16 on the GPU keeps its CPU figures those of float32."""
    if device.type == "cpu":
        return torch.bfloat16 if cpu_precision == "bf16" else None
    if device.type != "cuda" or precision == "32":
        return None
    return torch.bfloat16 if precision == "bf16" else torch.float16


def autocast(precision: str, device: torch.device, cpu_precision: str = "32"):
    """The run's autocast context on `device` (a no-op where amp_dtype is None): training, validation, evaluate.py
    and the apps compute alike."""
    dtype = amp_dtype(precision, device, cpu_precision)
    return contextlib.nullcontext() if dtype is None else torch.autocast(device.type, dtype=dtype)


def on_for_cuda(setting, device: torch.device) -> bool:
    """A GPU-first switch (trainer.channels_last, trainer.compile): "auto" is on for CUDA and off on the CPU, where
    it would change the figures or cost more than it gives; true/false as given."""
    return device.type == "cuda" if setting == AUTO else bool(setting)
