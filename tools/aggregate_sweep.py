"""Gather a Hydra sweep's metrics.jsonl files into markdown tables, mean ± std over seeds.

    python tools/aggregate_sweep.py multirun/crossview/2025-01-01_12-00-00_4242 [--at last|best|both] [--monitor R@1]
        [--metrics R@1,R@5,R@10,R@1%] [--out FILE]

Each run dir (any folder below MULTIRUN_DIR with a metrics.jsonl) gives its validation records (the keys `val/...`),
each tied to its epoch by the end-of-epoch row (`train/epoch_...`) the trainer writes after it. `--at last` takes
each run's last record; `--at best` the record of its best epoch: the best value of the metric the run's
trainer monitored (logged in metrics.jsonl as run/monitor and run/monitor_mode; `--monitor` picks another, highest
first), the earliest of equal ones, as the trainer picks best.pt; `--at both` (default) prints both tables. The
epoch column is the mean ± std of those epochs, counted from 0 as in metrics.jsonl, checkpoints and the trainer's `[epoch N]` lines.
Runs are grouped by their Hydra overrides (`.hydra/overrides.yaml`, else the dir name) minus `seed=`; overrides
that every run shares (dataset.root, ...) are left out of the row names. Recall values are shown in %; std is the
sample standard deviation (n - 1), blank for a single seed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import yaml

AT = ("last", "best")
TITLES = {"last": "last epoch", "best": "best epoch (highest {monitor} of each run)"}


def validations(metrics_file: Path) -> list[dict[str, float]]:
    """The run's validation records in epoch order, each with its `epoch`.

    The trainer logs a validation row, then the epoch's `train/epoch_*` row (whose `train/epoch_epoch` is the
    epoch). A validation row that another one follows before any epoch row belongs to an attempt that was killed
    and redone on resume: the later one counts. A final validation row with no epoch row after it (the run stopped
    in between) counts, for the epoch after the last one that ended.
    """
    by_epoch: dict[int, dict[str, float]] = {}
    pending, next_epoch = None, 0
    for line in metrics_file.read_text().splitlines():
        record = json.loads(line) if line.strip() else {}
        val = {k[4:]: v for k, v in record.items() if k.startswith("val/") and isinstance(v, (int, float))}
        if val:
            pending = val
        if any(k.startswith("train/epoch_") for k in record):
            epoch = int(record.get("train/epoch_epoch", next_epoch))
            next_epoch = epoch + 1
            if pending is not None:
                by_epoch[epoch] = {**pending, "epoch": epoch}  # a redone epoch replaces the first attempt
                pending = None
    if pending is not None:
        by_epoch[next_epoch] = {**pending, "epoch": next_epoch}
    return [by_epoch[e] for e in sorted(by_epoch)]


def recorded_monitor(metrics_file: Path) -> tuple[str, str] | None:
    """(metric, "max" | "min") that selected the run's best.pt, as the trainer logged it; None if it logged none."""
    for line in metrics_file.read_text().splitlines():
        record = json.loads(line) if line.strip() else {}
        if "run/monitor" in record:
            return record["run/monitor"], record.get("run/monitor_mode", "max")
    return None


def pick(records: list[dict[str, float]], at: str, monitor: str, source: Path | None = None, mode: str = "max"):
    """The last record, or the best one: the highest (mode max) or lowest (min) `monitor`, the earliest of equal
    ones (the trainer's strict comparison)."""
    if at == "last":
        return records[-1]
    scored = [r for r in records if monitor in r]
    if not scored:
        keys = sorted({k for r in records for k in r} - {"epoch"})
        raise ValueError(f"{source or 'a run'} has no val/{monitor} to pick the best epoch by; it logs {keys}. "
                         f"Pass --monitor with one of those, or --at last.")
    sign = 1.0 if mode == "max" else -1.0
    return max(scored, key=lambda r: sign * r[monitor])  # max() returns the first of equal maxima


def run_overrides(run_dir: Path) -> list[str]:
    saved = run_dir / ".hydra" / "overrides.yaml"
    if saved.is_file():
        return [str(x) for x in yaml.safe_load(saved.read_text()) or []]
    name = run_dir.name.split("_", 1)[-1] if run_dir.name.split("_", 1)[0].isdigit() else run_dir.name
    return [x for x in name.split(",") if x]


def collect(multirun_dir: Path, at: str = "last", monitor: str | None = None) -> list[tuple[list[str], dict]]:
    """[(overrides, the run's last or best validation record)] for each run that validated at least once. The best
    epoch is picked by `monitor` (max), else by the metric and mode each run recorded."""
    runs = []
    for metrics_file in sorted(multirun_dir.rglob("metrics.jsonl")):
        records = validations(metrics_file)
        if not records:
            continue
        chosen, mode = (monitor, "max") if monitor else (recorded_monitor(metrics_file) or (None, "max"))
        if at != "last" and chosen is None:
            raise ValueError(f"{metrics_file} records no monitored metric (a run by an older geoloc): pass --monitor")
        runs.append((run_overrides(metrics_file.parent), pick(records, at, chosen, metrics_file, mode)))
    return runs


def group(runs) -> dict[str, list[dict[str, float]]]:
    """{override string without seed= and without the overrides all runs share: [validation records]}."""
    keyed = [([o for o in overrides if not o.split("=", 1)[0].lstrip("+~") == "seed"], val) for overrides, val in runs]
    shared = set.intersection(*(set(o) for o, _ in keyed)) if len(keyed) > 1 else set()
    groups: dict[str, list[dict[str, float]]] = {}
    for overrides, val in keyed:
        name = " ".join(o for o in overrides if o not in shared) or "(base)"
        groups.setdefault(name, []).append(val)
    return groups


def fmt(values: list[float], percent: bool) -> str:
    scale = 100.0 if percent else 1.0
    mean = statistics.fmean(values) * scale
    if len(values) < 2:
        return f"{mean:.2f}"
    return f"{mean:.2f} ± {statistics.stdev(values) * scale:.2f}"


def table(groups: dict[str, list[dict[str, float]]], metrics: list[str] | None = None) -> str:
    if not groups:
        raise ValueError("no run with a validation record (metrics.jsonl with val/ keys) found")
    if metrics is None:
        first = next(iter(groups.values()))[0]
        metrics = [k for k in first if k.startswith("R@")] or [k for k in first if k != "epoch"]
    columns = ["epoch", *metrics]
    lines = ["| run | seeds | " + " | ".join(columns) + " |", "|---|---|" + "---|" * len(columns)]
    for name, records in groups.items():
        cells = [fmt([r[m] for r in records if m in r], m.startswith("R@")) if any(m in r for r in records) else "–"
                 for m in columns]
        lines.append(f"| {name} | {len(records)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def tables(multirun_dir: Path, at: str = "both", monitor: str | None = None, metrics: list[str] | None = None) -> str:
    """One table for `at` = last or best; for both, each under a markdown heading."""
    if at in AT:
        return table(group(collect(multirun_dir, at, monitor)), metrics)
    recorded = {recorded_monitor(f) for f in multirun_dir.rglob("metrics.jsonl")} - {None}
    named = monitor or (next(iter(recorded))[0] if len(recorded) == 1 else "the monitored metric")
    parts = []
    for one in AT:
        parts.append(f"### {TITLES[one].format(monitor=named)}\n\n"
                     + table(group(collect(multirun_dir, one, monitor)), metrics))
    return "\n\n".join(parts)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("multirun_dir", type=Path)
    parser.add_argument("--at", choices=[*AT, "both"], default="both",
                        help="each run's last validation, its best epoch's, or both tables (default)")
    parser.add_argument("--monitor", default=None,
                        help="the metric that picks the best epoch (default: the one each run's trainer monitored)")
    parser.add_argument("--metrics", default=None, help="comma-separated, e.g. R@1,R@5 (default: all R@ keys)")
    parser.add_argument("--out", type=Path, default=None, help="also write the tables to this file")
    args = parser.parse_args(argv)
    if not args.multirun_dir.is_dir():
        parser.error(f"{args.multirun_dir} is not a directory")
    text = tables(args.multirun_dir, args.at, args.monitor, args.metrics.split(",") if args.metrics else None)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return text


if __name__ == "__main__":
    sys.exit(main() and 0)
