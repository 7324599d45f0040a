"""The runs of a Hydra sweep folder and their names: what `tools/aggregate_sweep.py` (metrics.jsonl) and
`geoloc bench` (best.pt) read."""

from __future__ import annotations

from pathlib import Path

import yaml


def job_of(run_dir: Path, multirun_dir: Path) -> Path:
    """The sweep job a metrics folder belongs to: the nearest folder up to the sweep's that Hydra wrote .hydra/
    into (MMDIP's phase1/ and phase2/ log below their job's folder); the folder itself when none did."""
    for folder in (run_dir, *run_dir.parents):
        if (folder / ".hydra").is_dir():
            return folder
        if folder == multirun_dir:
            break
    return run_dir


def run_overrides(job: Path) -> list[str]:
    """The job's command-line overrides as Hydra saved them; without .hydra/, the folder's name stands for them."""
    saved = job / ".hydra" / "overrides.yaml"
    if saved.is_file():
        return [str(x) for x in yaml.safe_load(saved.read_text()) or []]
    return [job.name]


def shared_overrides(runs: list[list[str]]) -> set[str]:
    """The overrides every run of several shares (dataset.root, ...), which their names leave out."""
    return set.intersection(*(set(o) for o in runs)) if len(runs) > 1 else set()
