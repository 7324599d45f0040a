"""Which device a run or an app computes on: one rule for the trainer, evaluate.py and the apps."""

from __future__ import annotations

import torch

AUTO = "auto"


def valid_devices() -> list[str]:
    """The device names this machine takes: auto, cpu, and cuda, cuda:0 .. cuda:N-1 where CUDA is available."""
    names = [AUTO, "cpu"]
    if torch.cuda.is_available():
        names += ["cuda", *(f"cuda:{i}" for i in range(torch.cuda.device_count()))]
    return names


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
