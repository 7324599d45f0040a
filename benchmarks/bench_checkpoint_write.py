"""How much a background checkpoint write slows the training thread, for a few ways of writing it.

The trainer serialises last.pt on a background thread while the next epoch trains (geoloc/engine/checkpoint.py).
On one GPU machine the steps that ran beside that write were about 13% slower (benchmarks/README.md, "bench_train.py
--fit on a GPU"). This script separates the write from training: a stand-in for the training thread (on CUDA: a few
matrix products on the GPU, then a synchronisation, as a step with a loss read back; on the CPU: small products)
runs alone, then beside each way of writing a state of --mb MB, and prints its rate during the write against alone.
On CUDA it also times the copy of the state to the CPU that the writer makes before training goes on.

Ways of writing (each to a temp file, fsynced and renamed, as save_atomic does):
- file: save_atomic, the trainer's: `torch.save` into an open Python file object, without the zip's CRC-32s;
- crc: the same with torch's default, a CRC-32 of each record (how save_atomic wrote before);
- path: `torch.save` given the temp file's path (torch's C++ writer opens it), then fsync;
- raw: every tensor's bytes written with numpy's tofile, no zip (a lower bound: what the disk costs).

    python benchmarks/bench_checkpoint_write.py [--device cuda] [--mb 938] [--dir /tmp]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from geoloc.engine.checkpoint import renamed_into, save_atomic  # noqa: E402


def state_of(mb: int) -> dict:
    """A state dict of about `mb` MB in float32 tensors of a VGG16's sizes (a few large, many small)."""
    sizes = [102_760_448, 16_777_216, 2_359_296, 2_359_296, 1_179_648, 589_824, 294_912, 147_456, 73_728, 36_864]
    state, total, i = {}, 0, 0
    while total < mb * 1e6:
        n = sizes[i % len(sizes)]
        state[f"t{i}"] = torch.rand(n)
        total, i = total + 4 * n, i + 1
    return state


def write_path(state: dict, path: Path) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    with renamed_into(tmp, path):
        torch.save(state, tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())


def write_crc(state: dict, path: Path) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    with renamed_into(tmp, path), os.fdopen(fd, "wb") as f:
        torch.save(state, f)
        f.flush()
        os.fsync(f.fileno())


def write_raw(state: dict, path: Path) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    with renamed_into(tmp, path), os.fdopen(fd, "wb") as f:
        for value in state.values():
            value.numpy().tofile(f)
        f.flush()
        os.fsync(f.fileno())


WRITERS = {"file": save_atomic, "crc": write_crc, "path": write_path, "raw": write_raw}


def stand_in(device: torch.device):
    """One 'step' of the training thread: a few products, then waiting for them (as reading a loss back does)."""
    n = 4096 if device.type == "cuda" else 96
    x = torch.rand(n, n, device=device)

    def step():
        y = x
        for _ in range(8):
            y = torch.tanh(y @ x) * 0.01
        if device.type == "cuda":
            torch.cuda.synchronize()
        return y

    return step


def rate(step, seconds: float, until: threading.Thread | None = None) -> float:
    """Steps per second, for `seconds`, or while `until` runs."""
    t0, n = time.perf_counter(), 0
    while (until.is_alive() if until is not None else time.perf_counter() - t0 < seconds):
        step()
        n += 1
    return n / (time.perf_counter() - t0)


def copy_times(state: dict, device: torch.device) -> list[float]:
    """The copy of a GPU state to the CPU that the writer makes before training goes on (checkpoint.on_cpu), 3
    times: the first allocates its pinned memory, the others find it in torch's host allocator's cache."""
    from geoloc.engine.checkpoint import on_cpu

    on_gpu = {k: v.to(device) for k, v in state.items()}
    times = []
    for _ in range(3):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        copy = on_cpu(on_gpu)
        times.append(time.perf_counter() - t0)
        del copy
    print(f"copy of the state to the CPU: {', '.join(f'{t:.3f}' for t in times)} s", flush=True)
    return times


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--mb", type=int, default=938, help="state size (938: the paper size's last.pt)")
    p.add_argument("--dir", default=None, help="where to write (default: a temp folder)")
    p.add_argument("--writers", default="file,crc,path,raw")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    folder = Path(tempfile.mkdtemp(prefix="geoloc_bench_write_", dir=args.dir))
    state, step = state_of(args.mb), stand_in(device)
    for _ in range(3):
        step()
    results = {}
    for name in args.writers.split(","):
        alone = rate(step, 2.0)
        thread = threading.Thread(target=WRITERS[name], args=(state, folder / "last.pt"))
        t0 = time.perf_counter()
        thread.start()
        beside = rate(step, 0.0, until=thread)
        thread.join()
        write_s = time.perf_counter() - t0
        results[name] = {"alone_steps_s": alone, "beside_steps_s": beside, "ratio": beside / alone, "write_s": write_s}
        print(f"{name:6s} write {write_s:5.2f} s of {args.mb} MB; stand-in step {alone:7.1f}/s alone, {beside:7.1f}/s "
              f"beside the write: {beside / alone:.3f}", flush=True)
    if device.type == "cuda":
        results["copy"] = copy_times(state, device)
    for path in folder.iterdir():
        path.unlink()
    folder.rmdir()
    return results


if __name__ == "__main__":
    main()
