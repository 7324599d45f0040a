"""Gather a Hydra sweep's metrics.jsonl files into markdown tables, mean ± std over seeds.

    python tools/aggregate_sweep.py multirun/crossview/2025-01-01_12-00-00_4242 [--at last|best|both] [--monitor R@1]
        [--monitor-mode max|min] [--metrics R@1,R@5,R@10,R@1%] [--out FILE]

Each run dir (any folder below MULTIRUN_DIR with a metrics.jsonl) gives its validation records (the keys `val/...`),
each tied to its epoch by the end-of-epoch row (`train/epoch_...`) the trainer writes after it. `--at last` takes
each run's last record; `--at best` the record of its best epoch: the best value of the metric the run's
trainer monitored (logged in metrics.jsonl as run/monitor and run/monitor_mode), the earliest of equal ones, as the
trainer picks best.pt; `--at both` (default) prints both tables, the best one titled with what it picked. `--monitor`
picks another metric, its better direction from `--monitor-mode`, else the mode the run recorded for that metric,
else the direction geoloc's metric declares (an error in metres or degrees: the lowest; a share such as recall: the
highest); a metric none of them knows is refused, naming --monitor-mode. The
epoch column is the mean ± std of those epochs, counted from 0 as in metrics.jsonl, checkpoints and the trainer's `[epoch N]` lines.
Runs are grouped by their job's Hydra overrides (`.hydra/overrides.yaml` of the job folder, which MMDIP's phase1/
and phase2/ logs sit below; else the folder's name) minus `seed=`, and by phase; overrides that every run shares
(dataset.root, ...) are left out of the row names. A job that failed (a .hydra/ folder without metrics.jsonl), a
run that stopped before its last epoch (trainer.max_epochs in .hydra/config.yaml) or whose log ends in a cut
line is left out of the means and listed under the tables; a damaged line elsewhere stops the tool, naming the
file and line. Recall values are shown in %; std is the
sample standard deviation (n - 1), blank for a single seed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import yaml

from geoloc.launch.sweep_jobs import job_of, run_overrides, shared_overrides

AT = ("last", "best")
TITLES = {"last": "last epoch", "best": "best epoch ({picked} of each run)"}
EXTREMES = {"max": "highest", "min": "lowest"}


def rows(metrics_file: Path) -> tuple[list[dict], bool]:
    """(the JSON rows of a metrics.jsonl, whether its last line was cut). A run killed while writing leaves a cut
    last line, which is skipped (the run is then partial); a line that is not JSON anywhere else raises, naming the
    file and line."""
    lines = metrics_file.read_text().splitlines()
    out, cut = [], False
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError as err:
            if number == len(lines):
                cut = True
                continue
            raise ValueError(f"{metrics_file}:{number}: not a JSON line ({err.msg}): {line[:80]!r}. The file is "
                             "damaged; remove that line or the run from the sweep.") from None
    return out, cut


def validations(metrics_file: Path) -> list[dict[str, float]]:
    """The run's validation records in epoch order, each with its `epoch`.

    The trainer logs a validation row, then the epoch's `train/epoch_*` row (whose `train/epoch_epoch` is the
    epoch). A validation row that another one follows before any epoch row belongs to an attempt that was killed
    and redone on resume: the later one counts. A final validation row with no epoch row after it (the run stopped
    in between) counts, for the epoch after the last one that ended.
    """
    by_epoch: dict[int, dict[str, float]] = {}
    pending, next_epoch = None, 0
    for record in rows(metrics_file)[0]:
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
    for record in rows(metrics_file)[0]:
        if "run/monitor" in record:
            return record["run/monitor"], record.get("run/monitor_mode", "max")
    return None


def monitor_of(metrics_file: Path, monitor: str | None = None,
               mode: str | None = None) -> tuple[str | None, str | None]:
    """(metric, "max" | "min") that picks a run's best epoch: the run's own (recorded_monitor; (None, None) if it
    logged none) unless `monitor` names another, whose direction is `mode`, else the one the run recorded for it,
    else the one geoloc's metric declares (geoloc.tasks.crossview.validation_keys.known_mode), else None."""
    recorded = recorded_monitor(metrics_file)
    if monitor is None:
        return recorded or (None, None)
    if mode is None and recorded is not None and recorded[0] == monitor:
        mode = recorded[1]
    if mode is None:
        from geoloc.tasks.crossview.validation_keys import known_mode

        mode = known_mode(monitor)
    return monitor, mode


def pick(records: list[dict[str, float]], at: str, monitor: str, source: Path | None = None,
         mode: str | None = "max"):
    """The last record, or the best one: the highest (mode max) or lowest (min) `monitor`, the earliest of equal
    ones (the trainer's strict comparison); mode None: refused, naming --monitor-mode."""
    if at == "last":
        return records[-1]
    scored = [r for r in records if monitor in r]
    if not scored:
        keys = sorted({k for r in records for k in r} - {"epoch"})
        raise ValueError(f"{source or 'a run'} has no val/{monitor} to pick the best epoch by; it logs {keys}. "
                         f"Pass --monitor with one of those, or --at last.")
    if mode is None:
        raise ValueError(f"--monitor {monitor}: whether higher or lower is better is neither recorded in "
                         f"{source or 'the run'} nor declared by geoloc's metrics; pass --monitor-mode max (higher is "
                         "better) or min (lower is better)")
    sign = 1.0 if mode == "max" else -1.0
    return max(scored, key=lambda r: sign * r[monitor])  # max() returns the first of equal maxima


def planned_epochs(job: Path, run_dir: Path) -> int | None:
    """The epochs the run was asked for (trainer.max_epochs, capped by an MMDIP phase's own), from .hydra."""
    saved = job / ".hydra" / "config.yaml"
    if not saved.is_file():
        return None
    config = yaml.safe_load(saved.read_text()) or {}
    epochs = (config.get("trainer") or {}).get("max_epochs")
    phase = {"phase1": "segmentation", "phase2": "translation"}.get(run_dir.name)
    if phase and epochs is not None:
        own = ((config.get("task") or {}).get(phase) or {}).get("epochs")
        epochs = min(epochs, own) if own is not None else epochs
    return epochs


def collect(multirun_dir: Path, at: str = "last", monitor: str | None = None,
            problems: list[str] | None = None, mode: str | None = None) -> list[tuple[list[str], dict]]:
    """[(overrides, the run's last or best validation record)] for each complete run that validated. The best
    epoch is picked by monitor_of(its metrics.jsonl, monitor, mode). Jobs that failed (no
    metrics.jsonl, or no validation) and runs that stopped before their last epoch are left out of the tables and
    described in `problems`, so no job is dropped without a word."""
    problems = [] if problems is None else problems
    runs, seen = [], set()
    for metrics_file in sorted(multirun_dir.rglob("metrics.jsonl")):
        run_dir = metrics_file.parent
        job = job_of(run_dir, multirun_dir)
        seen.add(job)
        phase = f" ({run_dir.name})" if run_dir != job else ""
        records = validations(metrics_file)
        if not records:
            problems.append(f"{job}{phase}: no validation in {metrics_file} (failed or killed before its first one)")
            continue
        planned, cut = planned_epochs(job, run_dir), rows(metrics_file)[1]
        if cut or (planned is not None and records[-1]["epoch"] + 1 < planned):
            problems.append(f"{job}{phase}: partial, validated up to epoch {records[-1]['epoch']} of "
                            f"{planned if planned is not None else '?'}{' (its last line was cut)' if cut else ''}")
            continue
        chosen, direction = monitor_of(metrics_file, monitor, mode)
        if at != "last" and chosen is None:
            raise ValueError(f"{metrics_file} records no monitored metric (a run by an older geoloc): pass --monitor")
        overrides = run_overrides(job) + ([f"phase={run_dir.name}"] if phase else [])
        runs.append((overrides, pick(records, at, chosen, metrics_file, direction)))
    for hydra in sorted(multirun_dir.rglob(".hydra")):
        if hydra.parent not in seen and hydra.parent != multirun_dir:
            problems.append(f"{hydra.parent}: failed, no metrics.jsonl (see the job's log there)")
    return runs


def group(runs) -> dict[str, list[dict[str, float]]]:
    """{override string without seed= and without the overrides all runs share: [validation records]}."""
    keyed = [([o for o in overrides if not o.split("=", 1)[0].lstrip("+~") == "seed"], val) for overrides, val in runs]
    shared = shared_overrides([o for o, _ in keyed])
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


def table(groups: dict[str, list[dict[str, float]]], metrics: list[str] | None = None,
          problems: list[str] = ()) -> str:
    if not groups:
        raise ValueError("no complete run with a validation record (metrics.jsonl with val/ keys) found"
                         + "".join(f"\n- {p}" for p in problems))
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


def picked(multirun_dir: Path, monitor: str | None = None, mode: str | None = None) -> str:
    """What the best-epoch table picks, in words: "highest R@1", "lowest fine_median_m", or, where the runs differ,
    each run's own."""
    chosen = {monitor_of(f, monitor, mode) for f in multirun_dir.rglob("metrics.jsonl")}
    if len(chosen) != 1 or None in next(iter(chosen)):
        return "the best value of the metric each run monitored, in its own direction"
    metric, direction = next(iter(chosen))
    return f"{EXTREMES[direction]} {metric}"


def tables(multirun_dir: Path, at: str = "both", monitor: str | None = None, metrics: list[str] | None = None,
           mode: str | None = None) -> str:
    """One table for `at` = last or best; for both, each under a markdown heading. Failed and partial jobs are
    listed after the tables."""
    problems: list[str] = []
    if at in AT:
        runs = collect(multirun_dir, at, monitor, problems, mode)
        text = table(group(runs), metrics, problems)
    else:
        parts = []
        for one in AT:
            problems = []
            runs = collect(multirun_dir, one, monitor, problems, mode)  # refuses first what cannot be picked
            title = TITLES[one].format(picked=picked(multirun_dir, monitor, mode))
            parts.append(f"### {title}\n\n" + table(group(runs), metrics, problems))
        text = "\n\n".join(parts)
    if problems:
        text += "\n\nNot in the tables:\n" + "\n".join(f"- {p}" for p in problems)
    return text


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("multirun_dir", type=Path)
    parser.add_argument("--at", choices=[*AT, "both"], default="both",
                        help="each run's last validation, its best epoch's, or both tables (default)")
    parser.add_argument("--monitor", default=None,
                        help="the metric that picks the best epoch (default: the one each run's trainer monitored)")
    parser.add_argument("--monitor-mode", choices=["max", "min"], default=None,
                        help="with --monitor: whether its highest or lowest value is best (default: the mode the runs "
                             "recorded for it, else the direction geoloc's metric declares)")
    parser.add_argument("--metrics", default=None, help="comma-separated, e.g. R@1,R@5 (default: all R@ keys)")
    parser.add_argument("--out", type=Path, default=None, help="also write the tables to this file")
    args = parser.parse_args(argv)
    if not args.multirun_dir.is_dir():
        parser.error(f"{args.multirun_dir} is not a directory")
    if args.monitor_mode and not args.monitor:
        parser.error("--monitor-mode goes with --monitor (each run's own monitor comes with its recorded mode)")
    text = tables(args.multirun_dir, args.at, args.monitor, args.metrics.split(",") if args.metrics else None,
                  args.monitor_mode)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return text


if __name__ == "__main__":
    sys.exit(main() and 0)
