"""The generation driver: argument checks, the marker file, workers, progress, resume.

`out` holds the marker `geoloc_synthetic.json` (layout, generator version, seed, counts, preset and the resolved
config). It is written first with `"complete": false` and rewritten with `true` after the split files, so:
- an empty or new `out` is generated into;
- a complete dataset with the same marker is returned at once;
- an interrupted one with the same marker is resumed (samples finished before are kept: each one leaves a record
  in `.geoloc_partial/` only after all its files were written; unrecorded samples are rendered again);
- any other non-empty directory is refused, and nothing in it is deleted or mixed.
"""
from __future__ import annotations

import contextlib
import fcntl
import json
import multiprocessing as mp
import os
import shutil
from dataclasses import asdict
from pathlib import Path

import cv2
from tqdm import tqdm

from . import layouts as LY
from . import u1652_layout, vigor_layout
from .world_config import OPTIONS, SynthConfig, resolve, resolve_options
from .samples import render_pair, render_place_views

VERSION = "1.0"
MARKER = "geoloc_synthetic.json"
PARTIAL = ".geoloc_partial"
# Layouts written by a module with check(cfg, opts), jobs(opts, train, val), run(cfg, opts, seed, kind, index,
# number, root) -> record, and finish(root, opts, jobs, records); optionally DERIVED (file names) and derived(root,
# cfg, opts), which writes them from the split files alone. The three older layouts are written below.
WRITERS = {"vigor": vigor_layout, "u1652": u1652_layout}


class DatasetMismatchError(RuntimeError):
    """`out` holds a synthetic dataset made with other arguments."""


def generate(layout: str, out, train: int | None = None, val: int | None = None, seed: int = 0,
             preset: str | None = None, workers: int = 1, progress: bool = True, **overrides) -> Path:
    """Write a synthetic dataset in `layout` ('cvusa', 'cvact', 'dynamic', 'vigor' or 'u1652') to `out` and return
    its path.

    train/val count pairs (cvusa, cvact), places (dynamic: two views each), panoramas per city (vigor: its
    same-area train and test splits) or buildings (u1652: train and test); None takes the preset's counts.
    Overrides are SynthConfig fields (sizes, style, appearance-gap controls) and the layout's options
    (VigorOptions, U1652Options). The same arguments give byte-identical files whatever the number of workers.
    """
    cfg, counts = resolve(layout, preset, overrides)
    opts = resolve_options(layout, preset, overrides)
    train = counts["train"] if train is None else train
    val = counts["val"] if val is None else val
    for name, v in (("train", train), ("val", val), ("seed", seed), ("workers", workers)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ValueError(f"{name} must be a non-negative integer, got {v!r}")
    if train + val < 1:
        raise ValueError("train + val must be at least 1")
    if workers < 1:
        raise ValueError("workers must be at least 1")
    if cfg.view_nuisance is not None and layout not in ("cvusa", "cvact"):
        raise ValueError(f"view_nuisance is drawn for the cross-view pairs of the cvusa and cvact layouts only; the "
                         f"{layout} layout renders its views without it: leave it null")
    root = Path(out)
    # the generator's tag is the name the renderer was published under; every cache already rendered carries it
    marker = {"generator": "geoloc.data.synthetic", "version": VERSION, "layout": layout, "seed": seed,
              "train": train, "val": val, "preset": preset, "config": cfg.as_dict()}
    if opts is not None:  # only the newer layouts' markers carry options, so older datasets stay valid
        marker["options"] = asdict(opts)
        WRITERS[layout].check(cfg, opts)
    with rendering(root):  # one process renders a folder; another waits, then finds it complete
        if _check_out(root, marker):
            if layout == "cvusa" and not (root / LY.POSITIONS_FILE).exists():  # rendered before positions.csv
                jobs = _jobs(layout, train, val)
                LY.write_cvusa_positions(root, {s: [n for js, _, n in jobs if js == s] for s in ("train", "val")})
            _derived(layout, root, cfg, opts, missing_only=True)
            return root
        return _render(layout, root, marker, cfg, opts, train, val, seed, workers, progress)


@contextlib.contextmanager
def rendering(root: Path):
    """Hold an exclusive lock on `<root>.lock` (beside the folder) while checking and rendering `root`. The OS drops
    it when the process ends, kill -9 included; a run that finds it held waits for the render to finish."""
    lock = root.with_name(root.name + ".lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"waiting for another process that is rendering {root} ...", flush=True)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _render(layout: str, root: Path, marker: dict, cfg, opts, train: int, val: int, seed: int, workers: int,
            progress: bool) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    write_marker(root, marker, complete=False)

    jobs = WRITERS[layout].jobs(opts, train, val) if layout in WRITERS else _jobs(layout, train, val)
    done = root / PARTIAL
    if done.is_dir():  # a render that was killed: its half-written files are ours to clear (we hold the lock)
        for stale in root.rglob(".*.tmp"):
            stale.unlink()
    done.mkdir(exist_ok=True)
    todo = [j for j in jobs if not (done / f"{j[2]:07d}.json").exists()]
    opts_dict = None if opts is None else asdict(opts)
    args = [(layout, cfg.as_dict(), opts_dict, seed, split, index, number, str(root))
            for split, index, number in todo]
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc=f"synthetic {layout}", unit="sample",
               disable=not progress)
    if workers == 1 or len(args) <= 1:
        for a in args:
            _run(a)
            bar.update()
    else:
        # spawn, not fork: a forked child can deadlock in OpenCV's thread pool if the parent used cv2 already
        with mp.get_context("spawn").Pool(workers, initializer=_init_worker) as pool:
            for _ in pool.imap_unordered(_run, args, chunksize=2):
                bar.update()
    bar.close()
    if layout in WRITERS:
        records = {n: json.loads((done / f"{n:07d}.json").read_text()) for _, _, n in jobs}
        WRITERS[layout].finish(root, opts, jobs, records)
        _derived(layout, root, cfg, opts)
    else:
        _finish(layout, root, jobs, done)
    shutil.rmtree(done)
    write_marker(root, marker, complete=True)
    return root


def default_cache() -> Path:
    """Where the embedded synthetic datasets are rendered: $GEOLOC_CACHE/synthetic (default ~/.cache/geoloc)."""
    return Path(os.environ.get("GEOLOC_CACHE", Path.home() / ".cache" / "geoloc")) / "synthetic"


def ensure_dataset(layout: str, root, preset: str | None, train: int | None, val: int | None, seed: int = 0,
                   workers: int = 1, **overrides) -> Path:
    """The training run's entry: generate the default dataset on first use, reuse it afterwards."""
    return generate(layout, root, train, val, seed=seed, preset=preset, workers=workers, **overrides)


def _check_out(root: Path, marker: dict) -> bool:
    """True if root already holds this exact, complete dataset; raise if it holds anything else."""
    if not root.exists():
        return False
    if not root.is_dir():
        raise NotADirectoryError(f"{root} exists and is not a directory")
    mpath = root / MARKER
    if not mpath.exists():
        if any(root.iterdir()):
            raise FileExistsError(
                f"{root} is not empty and holds no {MARKER}: it is not a geoloc synthetic dataset. Refusing to "
                "write into it (nothing was changed); choose an empty or new directory.")
        return False
    try:
        found = json.loads(mpath.read_text())
    except json.JSONDecodeError as err:
        raise DatasetMismatchError(f"{mpath} is not valid JSON ({err}); refusing to touch {root}") from err
    complete = found.pop("complete", False)
    if found != marker:
        diff = sorted(k for k in set(found) | set(marker) if found.get(k) != marker.get(k))
        if "config" in diff:
            fc, mc = found.get("config") or {}, marker["config"]
            diff.remove("config")
            diff += [f"config.{k}" for k in sorted(set(fc) | set(mc)) if fc.get(k) != mc.get(k)]
        raise DatasetMismatchError(
            f"{root} holds a synthetic dataset made with other arguments (differs in: {', '.join(diff)}). "
            "Nothing was changed; use another directory, or delete it yourself to regenerate.")
    return bool(complete)


def _derived(layout: str, root: Path, cfg: SynthConfig, opts, missing_only: bool = False) -> None:
    """The layout's derived files (WRITERS above): written after its split files, and again when a complete dataset
    lacks one (rendered before the file existed: its images stay as they are, the marker too)."""
    writer = WRITERS.get(layout)
    if not hasattr(writer, "derived"):
        return
    if missing_only and all((root / name).is_file() for name in writer.DERIVED):
        return
    writer.derived(root, cfg, opts)


def write_marker(root: Path, marker: dict, complete: bool) -> None:
    """The marker, written atomically; a renderer writes it complete only after every other file."""
    text = json.dumps({**marker, "complete": complete}, indent=1, sort_keys=True) + "\n"
    LY.write_bytes(root / MARKER, text.encode())


def vigor_marker(root: Path, reader: str) -> dict:
    """The marker of the complete synthetic vigor dataset at `root`, which `reader` (a tool, named in its refusals)
    renders more of in the same world. Refused: no marker, one that is not JSON, a render of another layout or one
    that did not finish, and a relit copy (relight.py), whose marker is its source's and whose one city is not."""
    path = Path(root) / MARKER
    if not path.is_file():
        raise FileNotFoundError(f"{root} holds no {MARKER}: {reader} reads a synthetic vigor dataset that geoloc "
                                "rendered (e.g. ~/.cache/geoloc/synthetic/vigor-vigor_medium-seed0)")
    try:
        marker = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON ({err}); render the dataset again into an empty folder") from err
    if marker.get("layout") != "vigor" or not marker.get("complete") or "options" not in marker:
        raise ValueError(f"{path}: {reader} needs a complete synthetic vigor dataset, found layout "
                         f"{marker.get('layout')!r}, complete={marker.get('complete')}")
    if "relit" in marker:
        raise ValueError(f"{path}: {root} is itself relit; give {reader} the dataset it came from "
                         f"({marker['relit']['source']})")
    return marker


def _jobs(layout: str, train: int, val: int) -> list[tuple[str, int, int]]:
    """(split, index within split, global number). cvusa/cvact numbers are 1-based; dynamic places 0-based."""
    first = 0 if layout == "dynamic" else 1
    jobs = [("train", i, first + i) for i in range(train)]
    return jobs + [("val", i, first + train + i) for i in range(val)]


def _init_worker() -> None:
    cv2.setNumThreads(1)


def _run(args) -> None:
    layout, cfg_dict, opts_dict, seed, split, index, number, root = args
    cfg, root = SynthConfig(**cfg_dict), Path(root)
    record = {"split": split, "rows": []}
    if layout in WRITERS:
        record = WRITERS[layout].run(cfg, OPTIONS[layout](**opts_dict), seed, split, index, number, root)
    elif layout == "dynamic":
        for view in render_place_views(cfg, seed, split, index):
            stem = LY.dynamic_stem(number, view["role"])
            LY.write_dynamic_view(root, stem, view)
            record["rows"].append(LY.dynamic_row(stem, number, view))
    else:
        pair = render_pair(cfg, seed, split, index, sphere=layout == "cvact")
        (LY.write_cvusa_sample if layout == "cvusa" else LY.write_cvact_sample)(root, number, pair)
    LY.write_bytes(root / PARTIAL / f"{number:07d}.json", json.dumps(record).encode())  # last: marks it done


def _finish(layout: str, root: Path, jobs, done: Path) -> None:
    numbers = {"train": [n for s, _, n in jobs if s == "train"], "val": [n for s, _, n in jobs if s == "val"]}
    if layout == "cvusa":
        LY.write_cvusa_splits(root, numbers)
    elif layout == "cvact":
        LY.write_cvact_mat(root, numbers)
    else:
        rows = {s: [] for s in numbers}
        for s, _, n in jobs:
            rows[s] += json.loads((done / f"{n:07d}.json").read_text())["rows"]
        LY.write_dynamic_splits(root, rows)
