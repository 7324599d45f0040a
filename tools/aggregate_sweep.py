"""Gather a Hydra sweep's metrics.jsonl files into one markdown table, mean ± std over seeds.

    python tools/aggregate_sweep.py multirun/crossview/2025-01-01_12-00-00_4242 [--metrics R@1,R@5,R@10,R@1%] [--out FILE]

Each run dir (any folder below MULTIRUN_DIR with a metrics.jsonl) gives its *last* validation record (the keys
`val/...`). Runs are grouped by their Hydra overrides (`.hydra/overrides.yaml`, else the dir name) minus `seed=`;
overrides that every run shares (dataset.root, ...) are left out of the row names. Recall values are shown in %;
std is the sample standard deviation (n - 1), blank for a single seed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import yaml


def last_validation(metrics_file: Path) -> dict[str, float] | None:
    last = None
    for line in metrics_file.read_text().splitlines():
        record = json.loads(line) if line.strip() else {}
        val = {k[4:]: v for k, v in record.items() if k.startswith("val/") and isinstance(v, (int, float))}
        if val:
            last = val
    return last


def run_overrides(run_dir: Path) -> list[str]:
    saved = run_dir / ".hydra" / "overrides.yaml"
    if saved.is_file():
        return [str(x) for x in yaml.safe_load(saved.read_text()) or []]
    name = run_dir.name.split("_", 1)[-1] if run_dir.name.split("_", 1)[0].isdigit() else run_dir.name
    return [x for x in name.split(",") if x]


def collect(multirun_dir: Path) -> list[tuple[list[str], dict[str, float]]]:
    runs = []
    for metrics_file in sorted(multirun_dir.rglob("metrics.jsonl")):
        val = last_validation(metrics_file)
        if val is not None:
            runs.append((run_overrides(metrics_file.parent), val))
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
    lines = ["| run | seeds | " + " | ".join(metrics) + " |", "|---|---|" + "---|" * len(metrics)]
    for name, records in groups.items():
        cells = [fmt([r[m] for r in records if m in r], m.startswith("R@")) if any(m in r for r in records) else "–"
                 for m in metrics]
        lines.append(f"| {name} | {len(records)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("multirun_dir", type=Path)
    parser.add_argument("--metrics", default=None, help="comma-separated, e.g. R@1,R@5 (default: all R@ keys)")
    parser.add_argument("--out", type=Path, default=None, help="also write the table to this file")
    args = parser.parse_args(argv)
    if not args.multirun_dir.is_dir():
        parser.error(f"{args.multirun_dir} is not a directory")
    text = table(group(collect(args.multirun_dir)), args.metrics.split(",") if args.metrics else None)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return text


if __name__ == "__main__":
    sys.exit(main() and 0)
