"""Which device a run or an app computes on: one rule for the trainer, evaluate.py and the apps."""

from __future__ import annotations

import contextlib
import logging
import re

import torch

AUTO = "auto"
log = logging.getLogger(__name__)


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
    ("32" | "bf16" | "auto", cpu_bf16) on the CPU; None (no autocast) for "32". The CPU's is a key of its own, off by
    default, so a recipe that asks for bf16 on the GPU keeps its CPU figures those of float32."""
    if device.type == "cpu":
        return torch.bfloat16 if cpu_bf16(cpu_precision) else None
    if device.type != "cuda" or precision == "32":
        return None
    return torch.bfloat16 if precision == "bf16" else torch.float16


def native_cpu_bf16() -> bool | None:
    """Whether oneDNN has a native bfloat16 path on this CPU (AVX-512 or AMX; torch's own test, which its CPU bf16
    kernels use): without one every bf16 operation is emulated. None where torch cannot say."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return None


def cpu_bf16(cpu_precision: str) -> bool:
    """Whether trainer.cpu_precision computes in bfloat16 on this CPU: "bf16" always, "auto" only where the CPU has
    a native bfloat16 path (native_cpu_bf16 is True; where torch cannot say, float32), "32" never."""
    return cpu_precision == "bf16" or (cpu_precision == AUTO and native_cpu_bf16() is True)


def log_cpu_precision(device: torch.device, cpu_precision: str, where: str) -> None:
    """Say what trainer.cpu_precision=auto resolved to on this CPU (an info line), or warn of an emulated bf16
    (warn_emulated_bf16); nothing for "32" or on CUDA."""
    if device.type == "cpu" and cpu_precision == AUTO:
        log.info("%s: trainer.cpu_precision=auto computes in %s on this CPU", where,
                 "bfloat16 (it has a native bfloat16 path)" if cpu_bf16(AUTO) else
                 "float32 (it has no native bfloat16 path that torch reports)")
    warn_emulated_bf16(device, cpu_precision, where)


def warn_emulated_bf16(device: torch.device, cpu_precision: str, where: str) -> bool:
    """Log a warning when a bfloat16 autocast is asked for on a CPU that would emulate it, and say what to do: the
    refine_vigor recipe's batch took 45 s under bf16 on an AVX2 CPU against 1.5 s in float32, where a CPU with
    AVX-512 bf16 trains it 1.6x faster than float32 (docs/architecture.md). where: the run or checkpoint it is
    about. -> whether it warned."""
    if device.type != "cpu" or cpu_precision != "bf16" or native_cpu_bf16() is not False:
        return False
    log.warning("%s: the CPU autocast is bfloat16 (trainer.cpu_precision=bf16), but this CPU has no native bfloat16 "
                "path (no AVX-512 or AMX: torch emulates it), so it computes many times slower than float32 (about "
                "30x measured on an AVX2 CPU). To train in float32, add trainer.cpu_precision=32 (or auto: bf16 "
                "only where the CPU has it) to train.py's "
                "command line; a checkpoint trained in bfloat16 is evaluated and served in bfloat16, as it trained.",
                where)
    return True


def autocast(precision: str, device: torch.device, cpu_precision: str = "32"):
    """The run's autocast context on `device` (a no-op where amp_dtype is None): training, validation, evaluate.py
    and the apps compute alike."""
    dtype = amp_dtype(precision, device, cpu_precision)
    return contextlib.nullcontext() if dtype is None else torch.autocast(device.type, dtype=dtype)


def on_for_cuda(setting, device: torch.device) -> bool:
    """A GPU-first switch (trainer.channels_last, trainer.compile): "auto" is on for CUDA and off on the CPU, where
    it would change the figures or cost more than it gives; true/false as given."""
    return device.type == "cuda" if setting == AUTO else bool(setting)
