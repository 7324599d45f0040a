"""Checkpoints are plain dicts, written atomically and loaded with weights_only=True.

The trainer writes them through a CheckpointWriter: the state is copied to the CPU when the epoch ends, then
serialised once on a background thread while the next epoch trains; best.pt is a hard link to (or, where the file
system has none, a copy of) the last.pt written in the same epoch."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import random
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch

from geoloc.config import ConfigError


def save_atomic(obj: dict, path: str | Path) -> None:
    """Write to a temp file in the same folder, fsync, then rename: a kill never leaves a half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    with renamed_into(tmp, path):
        os.fchmod(fd, 0o666 & ~umask())  # mkstemp makes 0600; a checkpoint gets the mode any new file would
        with os.fdopen(fd, "wb") as f:
            with _without_zip_crc():
                torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())


_CRC_SWITCH = threading.Lock()


@contextlib.contextmanager
def _without_zip_crc():
    """torch.save without the CRC-32 of each zip record: torch.load never checks them (a flipped byte inside a
    tensor loads all the same), and computing them took a third of a paper-size write (938 MB on a GPU machine:
    1.28 s against 0.81-0.91 s; benchmarks/bench_checkpoint_write.py). torch's switch is global: it is turned off
    for this save only, under a lock, and a torch without it (< 2.6) writes them as before."""
    try:
        from torch.utils.serialization import config
    except ImportError:
        yield
        return
    with _CRC_SWITCH:
        before, config.save.compute_crc32 = config.save.compute_crc32, False
        try:
            yield
        finally:
            config.save.compute_crc32 = before


def link_atomic(source: str | Path, path: str | Path) -> None:
    """`path` becomes the file `source` names, atomically: a hard link where the file system has them (no bytes
    written: a later save_atomic of `source` renames a new file over it and leaves this one as it is), else an
    fsynced copy."""
    source, path = Path(source), Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    with renamed_into(tmp, path):
        try:
            os.link(source, tmp)
        except OSError:  # no hard links here (some network and FUSE file systems): a copy, made durable
            shutil.copyfile(source, tmp)
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())


@contextlib.contextmanager
def renamed_into(tmp: str | Path, path: Path):
    """What the block writes to `tmp` becomes `path` in one rename; a failure removes `tmp` and leaves `path` as it
    was."""
    try:
        yield
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def on_cpu(obj: Any) -> Any:
    """`obj` with every tensor copied to the CPU (dicts, lists and tuples followed): the state as it is now, which a
    background write can serialise while training changes the live tensors. GPU tensors are copied without
    blocking into pinned memory (torch's host allocator keeps those blocks for the next epoch's copy), then waited
    for once: a pageable copy of a paper-size state (938 MB) kept the GPU idle for about 0.5 s."""
    copied_from_gpu = []

    def copy(value):
        if isinstance(value, torch.Tensor):
            if value.is_cuda:
                copied_from_gpu.append(value.device)
                return value.detach().to("cpu", non_blocking=True)
            return value.detach().to("cpu", copy=True)
        if isinstance(value, dict):
            return {k: copy(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return type(value)(copy(v) for v in value)
        return value

    out = copy(obj)
    for device in set(copied_from_gpu):
        torch.cuda.synchronize(device)  # the copies are complete before anyone reads them
    return out


class CheckpointWriter:
    """Writes one state per call to `path` (atomically) and links it to each of `also`, on a background thread.

    submit() first waits for the previous write (one write in flight at most) and raises its error if it failed;
    join() waits for the last one, and is called at the end of fit, also when training fails, so a finished
    epoch's last.pt is on disk whatever follows."""

    def __init__(self):
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def submit(self, state: dict, path: Path, also: tuple[Path, ...] = ()) -> None:
        self.join()
        state = on_cpu(state)  # before training goes on: the next step changes the live tensors
        self._thread = threading.Thread(target=self._write_catching, args=(state, path, also),
                                        name="geoloc-checkpoint", daemon=False)
        self._thread.start()

    def join(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._error is not None:
            error, self._error = self._error, None
            raise RuntimeError(f"writing a checkpoint failed: {error}") from error

    def _write_catching(self, state: dict, path: Path, also: tuple[Path, ...]) -> None:
        try:
            save_atomic(state, path)
            for other in also:
                link_atomic(path, other)
        except BaseException as err:  # raised in the training thread by the next submit() or join()
            self._error = err


def load(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """A geoloc checkpoint dict; a missing, empty, truncated or foreign file raises an error naming `path`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}. Pass ckpt=<run dir>/best.pt or last.pt.")
    if path.stat().st_size == 0:
        raise RuntimeError(f"could not read checkpoint {path}: it is empty (0 bytes), e.g. a copy that failed. "
                           "Use another last.pt/best.pt.")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # a truncated or foreign file; torch's own advice (weights_only=False) would be unsafe
        raise RuntimeError(f"could not read checkpoint {path}: it is {_unreadable(path, err)}") from err
    if not isinstance(state, dict) or not isinstance(state.get("task"), dict):
        held = f"a dict with keys {sorted(map(str, state))[:6]}" if isinstance(state, dict) else type(state).__name__
        raise RuntimeError(f"could not read checkpoint {path}: it holds {held}, not a geoloc checkpoint (a dict with "
                           "the task's weights under 'task'). Pass a last.pt/best.pt written by geoloc.")
    return state


def _unreadable(path: Path, err: Exception) -> str:
    """Why torch.load failed, in one line (torch's message runs to a page)."""
    with open(path, "rb") as f:
        if f.read(64).startswith(b"version https://git-lfs"):
            return "a Git LFS pointer, not the checkpoint itself: fetch it with `git lfs pull`"
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    refused = [line for line in lines if line.startswith("WeightsUnpickler error:")]
    if refused:  # a pickle of arbitrary Python objects: never written by geoloc's trainer
        return f"not a geoloc checkpoint: it holds objects a safe load refuses ({refused[0]})"
    return f"truncated, corrupt or not a geoloc last.pt/best.pt ({type(err).__name__}: {lines[0] if lines else ''})"


def umask() -> int:
    """The process umask, read without changing it where Linux shows it (os.umask can only read by setting)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    current = os.umask(0o022)
    os.umask(current)
    return current


def load_task_state(task: torch.nn.Module, state: dict, path, fresh: tuple[str, ...] = (),
                    hint: str = "Was it written by another task or an edited config?") -> None:
    """load_state_dict with an error naming the checkpoint and the keys when its network doesn't match `task`.

    Keys starting with a prefix in `fresh` are neither loaded nor checked: they keep `task`'s own values.
    """
    own = {k: v for k, v in task.state_dict().items() if not k.startswith(fresh)}
    saved = {k: v for k, v in state["task"].items() if not k.startswith(fresh)}
    missing = [k for k in own if k not in saved]
    unexpected = [k for k in saved if k not in own]
    shapes = [f"{k}: ckpt {tuple(saved[k].shape)} vs model {tuple(v.shape)}"
              for k, v in own.items() if k in saved and saved[k].shape != v.shape]
    if missing or unexpected or shapes:
        found = [f"mis-shaped {shapes[:4]}" if shapes else "", f"missing {missing[:4]}" if missing else "",
                 f"unexpected {unexpected[:4]}" if unexpected else ""]
        raise ConfigError(
            f"checkpoint {path} does not match the model built from its config: {len(missing)} missing, "
            f"{len(unexpected)} unexpected, {len(shapes)} mis-shaped tensors ({'; '.join(f for f in found if f)}). "
            f"{hint}")
    task.load_state_dict(saved, strict=not fresh)


def rng_state() -> dict[str, Any]:
    """All RNG states as types weights_only=True accepts (tensors, lists, ints, floats)."""
    np_state = np.random.get_state()
    py_state = random.getstate()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"keys": torch.from_numpy(np_state[1].astype(np.int64)), "pos": int(np_state[2]),
                  "has_gauss": int(np_state[3]), "cached_gaussian": float(np_state[4])},
        "python": [py_state[0], list(py_state[1]), py_state[2]],
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state(("MT19937", n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def weights_fingerprint(module: torch.nn.Module) -> str:
    """sha256 of a module's state (names, shapes, bytes): ties what was computed with the weights (a saved gallery)
    to the weights themselves, whatever file they were copied to."""
    h = hashlib.sha256()
    for name, tensor in sorted(module.state_dict().items()):
        h.update(name.encode())
        h.update(str(tuple(tensor.shape)).encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def init_from(task: torch.nn.Module, path: str | Path, fresh: tuple[str, ...] = ()) -> dict:
    """Load the network weights of checkpoint `path` into `task` (keys under the `fresh` prefixes keep their new
    values) and return the record of where they came from (`write_source` puts it in the run dir): a new run
    (epoch 0, fresh optimizer) that starts from another run's weights."""
    path = Path(path)
    state = load(path)
    load_task_state(task, state, path, fresh=fresh,
                    hint="init_from= needs the same network (model.*) as the checkpoint it starts from.")
    best = state.get("best_metric")
    return {"path": str(path.resolve()), "sha256": file_sha256(path), "epoch": state.get("epoch"),
            "global_step": state.get("global_step"), "monitor": state.get("monitor"),
            "best_metric": best if best is not None and math.isfinite(best) else None}


def write_source(run_dir: Path, record: dict) -> None:
    """run_dir/init_from.json: where an init_from= run's weights came from."""
    (Path(run_dir) / "init_from.json").write_text(json.dumps(record, indent=2) + "\n")


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
