"""Everything distributed lives here: start-up from the environment, rank queries and gathers.

torchrun sets RANK / WORLD_SIZE / LOCAL_RANK / MASTER_ADDR / MASTER_PORT; under SLURM without torchrun (srun, or
the submitit launcher with one task per GPU) we read SLURM_PROCID / SLURM_NTASKS / SLURM_LOCALID instead and, when
the job did not export them, derive MASTER_ADDR (the job's first node) and MASTER_PORT (from the job id).
Rank 0 owns all I/O: logs, checkpoints, pictures.
"""

from __future__ import annotations

import gc
import os
import re
import subprocess

import torch
import torch.distributed as dist

from geoloc.engine.device import resolve_device


def _env_int(*names: str, default: int) -> int:
    for name in names:
        if name in os.environ:
            return int(os.environ[name])
    return default


def init_from_env(device: str = "auto") -> torch.device:
    """Join the process group when launched by torchrun or SLURM, and return this rank's device.

    `device` is "auto", "cpu", "cuda" or "cuda:N" (one process only: under torchrun or SLURM each rank takes
    cuda:LOCAL_RANK). On CPU the backend is gloo, on CUDA nccl.
    """
    chosen = resolve_device(device)
    use_cuda = chosen.type == "cuda"
    world_size = _env_int("WORLD_SIZE", "SLURM_NTASKS", default=1)
    local_rank = _env_int("LOCAL_RANK", "SLURM_LOCALID", default=0)
    if use_cuda and chosen.index is not None and world_size > 1:
        raise ValueError(f"trainer.device={device} names one GPU, but this is a launch of {world_size} processes, "
                         "each of which takes the GPU of its local rank: set trainer.device=cuda")
    if use_cuda and chosen.index is not None:
        torch.cuda.set_device(chosen)
        return chosen
    if world_size > 1 and not dist.is_initialized():
        slurm_master_env()
        os.environ.setdefault("RANK", str(_env_int("RANK", "SLURM_PROCID", default=0)))
        os.environ.setdefault("WORLD_SIZE", str(world_size))
        if use_cuda:
            torch.cuda.set_device(local_rank)
        dist.init_process_group(backend="nccl" if use_cuda else "gloo")
    if use_cuda:
        return torch.device("cuda", local_rank if world_size > 1 else torch.cuda.current_device())
    return torch.device("cpu")


def first_host(nodelist: str) -> str:
    """The first host of a SLURM node list: "gpu[07-09,12],cpu1" -> "gpu07" (scontrol when available)."""
    try:
        out = subprocess.run(["scontrol", "show", "hostnames", nodelist], capture_output=True, text=True,
                             timeout=10, check=True).stdout.split()
        if out:
            return out[0]
    except (OSError, subprocess.SubprocessError):
        pass
    m = re.match(r"([^\[,]+)(?:\[([^\],-]+))?", nodelist)
    if not m:
        raise RuntimeError(f"cannot read the SLURM node list {nodelist!r}; export MASTER_ADDR in the job")
    return m.group(1) + (m.group(2) or "")


def slurm_master_env() -> None:
    """Under SLURM without torchrun, export MASTER_ADDR / MASTER_PORT unless the job already did.

    Every task of a job computes the same values: the first node of the job, and a port from the job id (so two
    jobs sharing a node do not collide).
    """
    if "SLURM_PROCID" not in os.environ or "RANK" in os.environ:
        return  # not SLURM, or torchrun (which sets the rendezvous itself)
    if "MASTER_ADDR" not in os.environ:
        nodes = os.environ.get("SLURM_JOB_NODELIST") or os.environ.get("SLURM_NODELIST") or ""
        single_node = int(os.environ.get("SLURM_JOB_NUM_NODES", os.environ.get("SLURM_NNODES", "1"))) == 1
        os.environ["MASTER_ADDR"] = "127.0.0.1" if single_node or not nodes else first_host(nodes)
    os.environ.setdefault("MASTER_PORT", str(20000 + int(os.environ.get("SLURM_JOB_ID", "0")) % 20000))


def launch_rank() -> int:
    """This process's rank as torchrun (RANK) or SLURM (SLURM_PROCID) set it, readable before the process group
    exists; 0 when the launch has one process."""
    if _env_int("WORLD_SIZE", "SLURM_NTASKS", default=1) == 1:
        return 0
    return _env_int("RANK", "SLURM_PROCID", default=0)


def is_dist() -> bool:
    return dist.is_available() and dist.is_initialized()


def rank() -> int:
    return dist.get_rank() if is_dist() else 0


def world_size() -> int:
    return dist.get_world_size() if is_dist() else 1


def is_main() -> bool:
    return rank() == 0


def barrier() -> None:
    if is_dist():
        dist.barrier()


def all_gather_nograd(tensor: torch.Tensor) -> torch.Tensor:
    """Concatenate `tensor` (same shape on every rank) over ranks along dim 0, rank order. No gradient."""
    if not is_dist():
        return tensor
    parts = [torch.empty_like(tensor) for _ in range(world_size())]
    dist.all_gather(parts, tensor.contiguous())
    return torch.cat(parts, dim=0)


def all_gather_with_grad(tensor: torch.Tensor) -> torch.Tensor:
    """Like `all_gather_nograd`, but gradients flow back to every rank's slice (torch.distributed.nn).

    Used so the exhaustive triplet loss sees the global batch under DDP.
    """
    if not is_dist():
        return tensor
    from torch.distributed.nn.functional import all_gather

    return torch.cat(all_gather(tensor.contiguous()), dim=0)


def all_gather_variable(tensor: torch.Tensor) -> torch.Tensor:
    """all_gather for tensors whose first dimension differs between ranks (e.g. the last validation shard)."""
    if not is_dist():
        return tensor
    n = torch.tensor([tensor.shape[0]], device=tensor.device)
    sizes = all_gather_nograd(n).tolist()
    padded = torch.zeros((max(sizes), *tensor.shape[1:]), dtype=tensor.dtype, device=tensor.device)
    padded[: tensor.shape[0]] = tensor
    gathered = all_gather_nograd(padded)
    step = max(sizes)
    return torch.cat([gathered[i * step : i * step + s] for i, s in enumerate(sizes)], dim=0)


def reduce_mean(value: float, device: torch.device) -> float:
    """Average a Python float over ranks (for logging)."""
    if not is_dist():
        return value
    t = torch.tensor([value], dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return (t / world_size()).item()


def cleanup() -> None:
    """Leave the process group. destroy_process_group() only forgets the group; objects that still hold it (a DDP
    wrapper in a reference cycle) keep its gloo threads alive until they are collected. Collected here, while the
    interpreter is alive: at interpreter finalisation gloo's teardown aborts the rank (SIGABRT, \"terminate called
    without an active exception\"), which torchrun reports as a failed run."""
    if is_dist():
        dist.destroy_process_group()
        gc.collect()
