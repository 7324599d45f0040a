"""A run owns its directory: one live run per folder, no run over another run's output, nothing left by a failure.

    with claimed(run_dir, ckpt=cfg.ckpt):   # lock, refuse a taken folder, clear a killed save's temp files
        trainer.fit(...)                     # a failure before any output removes the folder again

The lock is `fcntl.flock` on `run_dir/.lock`, held for the run's life; the OS drops it when the process ends, kill -9
included, so a dead run never blocks its folder. Only rank 0 of a launch claims: the other ranks write nothing.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import socket
from collections.abc import Iterator
from pathlib import Path

from geoloc.engine.distributed import launch_rank

LOCK = ".lock"
#: what a run leaves that a new run must not write over (mmdip writes phase1/ and phase2/)
RUN_OUTPUTS = ("*.pt", "metrics.jsonl", "phase*/*.pt", "phase*/metrics.jsonl")
#: temp files of a save that was killed before its rename (checkpoint.save_atomic names them so)
STALE_TEMP = (".*.pt.*.tmp", "phase*/.*.pt.*.tmp")


class RunDirTaken(RuntimeError):
    """The run dir is held by a live run, or holds another run's output."""


def run_outputs(run_dir: Path) -> list[Path]:
    return sorted(p for pattern in RUN_OUTPUTS for p in run_dir.glob(pattern))


def refuse_if_taken(run_dir: str | Path, ckpt: str | None = None, role: str = "training") -> None:
    """Raise RunDirTaken when a live run holds `run_dir`, or when it holds a run's output and `ckpt` does not
    point into it (a resume in place). A missing folder is free. Writes nothing."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        return
    if (run_dir / LOCK).is_file():
        fd = os.open(run_dir / LOCK, os.O_RDWR)  # NFS emulates flock with write locks
        try:
            _lock_or_refuse(fd, run_dir)
        finally:
            os.close(fd)  # closing drops the probe's lock
    _refuse_output(run_dir, ckpt, role)


@contextlib.contextmanager
def claimed(run_dir: str | Path, ckpt: str | None = None, role: str = "training",
            key: str = "hydra.run.dir") -> Iterator[Path]:
    """Own `run_dir` for the block: create it, lock it, refuse it when taken (see `refuse_if_taken`), remove
    temp files of a killed save. If the block fails before the run wrote anything (a config error, a missing
    dataset), the folder is removed, Hydra's `.hydra/` and log included. Ranks > 0 only get the path. `key`: the
    setting that chose the folder (localize.py's `out`), named in refusals."""
    run_dir = Path(run_dir)
    if launch_rank() > 0:
        yield run_dir
        return
    run_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(run_dir / LOCK, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        _lock_or_refuse(fd, run_dir, key)
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode())
        try:
            _refuse_output(run_dir, ckpt, role, key)
            for pattern in STALE_TEMP:
                for tmp in run_dir.glob(pattern):
                    tmp.unlink()
            yield run_dir
        except BaseException:
            if holds_nothing(run_dir) and not is_cwd_or_above(run_dir):
                shutil.rmtree(run_dir, ignore_errors=True)
            raise
    finally:
        os.close(fd)  # releases the lock


def holds_nothing(folder: Path, top: bool = True) -> bool:
    """True when `folder` holds only what Hydra and the lock put there before a run starts (`.hydra/`, the job's
    `*.log`, `.lock`) and empty folders."""
    for entry in folder.iterdir():
        if top and (entry.name in (".hydra", LOCK) or (entry.suffix == ".log" and entry.is_file())):
            continue
        if entry.is_dir() and not entry.is_symlink() and holds_nothing(entry, top=False):
            continue
        return False
    return True


def _lock_or_refuse(fd: int, run_dir: Path, key: str = "hydra.run.dir") -> None:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "a process that wrote no pid"
        raise RunDirTaken(
            f"run dir {run_dir} is in use by another live run ({holder}, per {run_dir / LOCK}). Two runs in one "
            f"folder would overwrite each other's outputs (checkpoints, metrics.jsonl, localize.jsonl). Choose "
            f"another {key} (or leave the default, which is unique), or wait for that run to end.") from None
    except OSError as err:  # e.g. ENOLCK: a file system without locks
        message = (f"cannot lock run dir {run_dir} ({err}): geoloc locks a run's folder so that no other run "
                   f"writes into it. Choose a hydra.run.dir on a file system with locks (local disk, NFSv4).")
        raise OSError(message) from err


def _refuse_output(run_dir: Path, ckpt: str | None, role: str = "training", key: str = "hydra.run.dir") -> None:
    """A training may write into a run dir with outputs only to resume it (`ckpt` in it); an evaluation or a
    localisation ("evaluation", "localization") never writes into a training's folder, whose .hydra/ record and
    metrics it would mix with its own."""
    outputs = run_outputs(run_dir)
    resumes = role == "training" and ckpt and Path(ckpt).resolve().parent == run_dir.resolve()
    if not outputs or resumes:
        return
    names = ", ".join(str(p.relative_to(run_dir)) for p in outputs[:6])
    if role != "training":
        raise RunDirTaken(f"run dir {run_dir} belongs to a training run ({names}); this {role} stopped before "
                          f"writing anything. An {role} writes its own folder: leave {key} at its default "
                          f"(a new outputs/<...>/<date>_<time>_<pid>) or choose one that holds no run.")
    last = run_dir / "last.pt"
    if last.is_file():
        ways = (f"To continue that run, resume it: ckpt={last} (add hydra.run.dir={run_dir} to keep writing there). "
                f"To start a new run, choose another hydra.run.dir or leave the default (a new "
                f"outputs/<task>/<dataset>/<date>_<time>_<pid>); add init_from={last} to start it from that run's "
                f"weights.")
    else:
        ways = ("It has no last.pt to resume from. To start a new run, choose another hydra.run.dir or leave the "
                "default (a new outputs/<task>/<dataset>/<date>_<time>_<pid>).")
    raise RunDirTaken(f"run dir {run_dir} already holds another run's output ({names}); this run stopped before "
                      f"training. {ways}")


def is_cwd_or_above(path: Path) -> bool:
    here, path = Path.cwd().resolve(), path.resolve()
    return here == path or path in here.parents
