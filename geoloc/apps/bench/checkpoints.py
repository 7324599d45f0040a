"""The checkpoints `geoloc bench` scores, from what the user names: a checkpoint file, a run folder (its best.pt),
or a sweep folder (the best.pt of each of its runs, named by the run's Hydra overrides as
tools/aggregate_sweep.py names them)."""

from __future__ import annotations

from pathlib import Path

from geoloc.config import ConfigError
from geoloc.launch.sweep_jobs import job_of, run_overrides, shared_overrides

BEST = "best.pt"


def checkpoints(paths: list[str]) -> list[tuple[str, Path]]:
    """[(name, checkpoint file)] in the order given (a sweep's runs sorted by path); a path that holds none is
    refused before anything is evaluated."""
    if not paths:
        raise ConfigError("ckpts=[...] is empty: give checkpoint files, run folders (best.pt) or a sweep folder")
    found: list[tuple[str, Path]] = []
    for given in paths:
        path = Path(given)
        if path.is_file():
            found.append((_file_name(path), path))
        elif (path / BEST).is_file():
            found.append((path.name, path / BEST))
        elif path.is_dir():
            found += sweep_runs(path)
        else:
            raise ConfigError(f"ckpts: {given} is neither a checkpoint file nor a folder")
    names = [name for name, _ in found]
    return [(str(file) if names.count(name) > 1 else name, file) for name, file in found]


def sweep_runs(sweep: Path) -> list[tuple[str, Path]]:
    """[(the run's overrides that not every run shares, its best.pt)] of each run below `sweep`."""
    files = sorted(sweep.rglob(BEST))
    if not files:
        raise ConfigError(f"ckpts: {sweep} holds no {BEST} in it or below it (no finished run)")
    overrides = [run_overrides(job_of(f.parent, sweep)) for f in files]
    shared = shared_overrides(overrides)
    return [(" ".join(o for o in own if o not in shared) or f.parent.name, f) for own, f in zip(overrides, files)]


def _file_name(path: Path) -> str:
    """A run's best.pt is named by its run folder; another file by itself."""
    return path.parent.name if path.name == BEST and path.parent.name else path.name
