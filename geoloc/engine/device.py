"""Which device a run or an app computes on: one rule for the trainer, evaluate.py and the apps."""

from __future__ import annotations

import torch

AUTO = "auto"


def resolve_device(device: str | None = None) -> torch.device:
    """None or "auto": the GPU when CUDA is available, else the CPU; "cpu", "cuda", "cuda:N" as given. A CUDA
    device where CUDA is not available is an error that says so."""
    name = AUTO if device is None else str(device)
    if name == AUTO:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        chosen = torch.device(name)
    except RuntimeError:
        raise ValueError(f"device={name!r} is not a device: use auto, cpu, cuda or cuda:N") from None
    if chosen.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device={name!r} but CUDA is not available on this machine; use device=cpu.")
    return chosen
