"""`geoloc bench ckpts=[...] sets=[...] fovs=[...] headings=[...]`: one table of many checkpoints on many test
sets under the FoV / heading protocols, beside the published figures; markdown printed, CSV and JSON written."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from geoloc.apps.bench import report
from geoloc.apps.bench.checkpoints import checkpoints
from geoloc.apps.bench.protocols import HEADINGS, PHOTO, protocols
from geoloc.apps.bench.encode_once import score_protocols
from geoloc.apps.bench.bench_sets import ROOT_KEYS, TEST_SETS, data_overrides, test_set
from geoloc.apps.table_files import (check_fovs, evaluate_config, refuse_out_that_is_no_folder, refuse_taken,
                                     write_whole)
from geoloc.config import ConfigError
from geoloc.launch.hydra_hooks import compose_checked

USAGE = f"""usage: geoloc bench ckpts=[PATH,...] [sets=[{','.join(TEST_SETS)}]] [fovs=[360,180,90,70]]
                    [headings=[known,unknown]] [heading_steps=12] [cvusa=DIR] [cvact=DIR] [vigor=DIR] [u1652=DIR]
                    [out=bench] [overwrite=false] [device=auto] [num_workers=0] [progress=true] [dataset.KEY=VALUE]

  ckpts             checkpoint files, run folders (their best.pt) or sweep folders (the best.pt of every run below,
                    named by the run's Hydra overrides)
  sets              the test sets; CVACT's val and test, VIGOR's same- and cross-area, University-1652's drone ->
                    satellite (d2s) and satellite -> drone (s2d)
  fovs, headings    the protocols of panorama queries: each FoV with the heading known (the view at north) and
                    unknown (searched over heading_steps candidate headings); photo queries (University-1652) are
                    scored at their own view alone
  cvusa ... u1652   a released dataset's root; without one, the test set runs on its embedded synthetic world, and
                    its rows say so
  out               the folder of bench.md, bench.csv and bench.json (existing ones refused unless overwrite=true)
  dataset.KEY       evaluate.py overrides applied to every test set (e.g. dataset.max_val=200: the first 200 queries)

Each row is evaluate.py's config and metrics; the references are encoded once per checkpoint and test set, the
queries once per protocol. The published figures come from geoloc/apps/bench/published.yaml (docs/bench.md)."""

FILES = ("bench.md", "bench.csv", "bench.json")


@dataclass
class BenchConfig:
    """`geoloc bench`'s own keys (schema/bench: geoloc/conf/bench.yaml); dataset.* overrides: split_args."""

    ckpts: list[str] = field(default_factory=list)
    sets: list[str] = field(default_factory=lambda: list(TEST_SETS))
    fovs: list[float] = field(default_factory=lambda: [360.0, 180.0, 90.0, 70.0])
    headings: list[str] = field(default_factory=lambda: list(HEADINGS))
    heading_steps: int = 12
    cvusa: str | None = None
    cvact: str | None = None
    vigor: str | None = None
    u1652: str | None = None
    out: str = "bench"
    overwrite: bool = False
    device: str = "auto"
    num_workers: int = 0
    progress: bool = True

    def __post_init__(self):
        check_fovs(self.fovs)
        if not self.headings or any(h not in HEADINGS for h in self.headings):
            raise ValueError(f"headings must be a non-empty list of {list(HEADINGS)}, got {self.headings}")
        if self.heading_steps < 1:
            raise ValueError(f"heading_steps must be >= 1, got {self.heading_steps}")


def split_args(args: list[str]) -> tuple[list[str], list[str]]:
    """(bench.yaml's overrides, the dataset.* overrides every test set gets: evaluate.py's, passed as given)."""
    own, dataset = [], []
    for arg in args:
        name = arg.partition("=")[0].lstrip("+~")
        if name == "dataset":
            raise ConfigError("sets= names the test sets; dataset= is not a geoloc bench key")
        (dataset if name.startswith("dataset.") else own).append(arg)
    return own, dataset


def bench(args: list[str]) -> dict:
    """Compute and write the table; returns its JSON record."""
    own, dataset = split_args(args)
    cfg = compose_checked("bench", BenchConfig, own, "bench")
    out = Path(cfg.out)
    refuse_out_that_is_no_folder(out, list(FILES), "geoloc bench")
    refuse_taken([out / name for name in FILES], cfg.overwrite)
    runs = checkpoints(cfg.ckpts)
    sets = [test_set(name) for name in cfg.sets]
    roots = {key: getattr(cfg, key) for key in ROOT_KEYS}
    panorama = protocols(cfg.fovs, cfg.headings, cfg.heading_steps)
    start, rows, notes = time.perf_counter(), [], []
    if any(not t.panorama for t in sets) and [(p.fov, p.heading) for p in panorama] != [(360.0, "known")]:
        notes.append("University-1652's queries are photos: scored at their own view alone (FoV 360, heading "
                     "known), not under the panorama protocols.")
    unreleased = [t.name for t in sets if t.released_only and not roots.get(t.root_key)]
    if unreleased:
        notes.append(f"{', '.join(unreleased)}: VIGOR's original labels, scored on a released root alone (vigor=DIR); "
                     "the embedded world has one label set, which the vigor_same / vigor_cross rows show.")
        sets = [t for t in sets if t.name not in unreleased]
    cells = tqdm([(run, t) for run in runs for t in sets], desc="bench", disable=not cfg.progress)
    for (name, ckpt), test in cells:
        cells.set_postfix_str(f"{name} on {test.name}")
        try:
            rows += bench_cell(name, ckpt, test, panorama if test.panorama else [PHOTO], roots, dataset, cfg)
        except ConfigError as refusal:  # evaluate.py refuses this checkpoint on this set: a note, not a stop
            notes.append(f"{name} on {test.name}: not scored, as evaluate.py refuses it: {refusal}")
    seconds = time.perf_counter() - start
    settings = {"ckpts": [{"name": n, "path": str(p)} for n, p in runs], "sets": list(cfg.sets),
                "fovs": list(cfg.fovs), "headings": list(cfg.headings), "heading_steps": cfg.heading_steps,
                "roots": roots, "dataset_overrides": dataset}
    table, record = report.markdown(rows, notes), report.record(rows, settings, notes, seconds)
    out.mkdir(parents=True, exist_ok=True)
    write_whole(out / "bench.json", json.dumps(record, indent=2) + "\n", cfg.overwrite)
    write_whole(out / "bench.csv", report.csv_text(rows), cfg.overwrite)
    write_whole(out / "bench.md", table, cfg.overwrite)
    print(f"\n{table}\nwritten: {', '.join(str(out / name) for name in FILES)} ({seconds:.0f} s)")
    return record


def bench_cell(name: str, ckpt: Path, test, chosen: list, roots: dict, dataset: list[str], cfg: BenchConfig):
    """The rows of one checkpoint on one test set: one per protocol."""
    from geoloc.engine import checkpoint as ckpt_io
    from geoloc.tasks.crossview.crossview_run import restored_task, stored_config

    data, synthetic = data_overrides(test, roots)
    configs = [evaluate_config(str(ckpt), [*data, *dataset, *p.overrides()], cfg.device, cfg.num_workers,
                               cfg.progress) for p in chosen]
    state = ckpt_io.load(ckpt)
    stored = stored_config(state)
    metrics, split = score_protocols(restored_task(state, ckpt, stored), stored, configs)
    return [{"checkpoint": name, "ckpt": str(ckpt), "test_set": test.name, "published_as": test.published_as,
             "synthetic": synthetic,
             "split": split["split"], "labels": split["labels"], "protocol": p.name, "fov": p.fov,
             "heading": p.heading, "overrides": [*data, *dataset, *p.overrides()], "metrics": m}
            for p, m in zip(chosen, metrics)]


def main(args: list[str]) -> int:
    bench(args)
    return 0
