"""`geoloc robustness ckpt=PATH ...`: one Markdown and one JSON table of a checkpoint under every test condition
(geoloc/apps/robustness/conditions.py), written whole into `out`."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import MISSING

from geoloc.apps.table_files import (check_fovs, evaluate_config, refuse_out_that_is_no_folder, refuse_taken,
                                     write_whole)
from geoloc.config import ConfigError
from geoloc.launch.hydra_hooks import compose_checked
from geoloc.apps.robustness.conditions import Plan, as_json, evaluate_conditions, markdown

USAGE = """usage: geoloc robustness ckpt=PATH [out=DIR] [overwrite=false] [fovs=[360,180,90,70]] [heading_steps=12]
                         [distractors=1000] [distractor_split=train] [cross=dataset=vigor] [device=auto]
                         [num_workers=0] [dataset=NAME dataset.root=DIR dataset.split=...]

  ckpt              a checkpoint written by train.py (best.pt)
  out               the folder of robustness.md and robustness.json (default: robustness_<checkpoint name>/
                    beside the checkpoint); existing files are refused unless overwrite=true
  fovs              the street view's fields of view, in degrees; each is scored with the heading known (the view
                    at north) and unknown (searched over heading_steps candidate headings)
  heading_steps     candidate headings of the unknown-heading search (12: every 30 degrees; evaluate.py's
                    default is 36)
  distractors       the rows again with the gallery padded by this many tiles of other places: the first tiles
                    of the same dataset's distractor_split that are not in the evaluated gallery (0: no padded
                    rows; none such, as in VIGOR same-area, whose splits share their tiles: none, and the table
                    says why)
  cross             evaluate.py overrides of a cross-dataset row (FoV 360, heading known), e.g.
                    cross="dataset=cvact dataset.root=/data/CVACT"; several rows separated by ';'; cross=none: none
  dataset*          evaluate.py's overrides of the data the main rows score (default: the checkpoint's own)

Every row runs evaluate.py's path (its config, then the same scoring); the same numbers come from
python evaluate.py ckpt=PATH dataset.fov=F dataset.random_heading=true dataset.heading_steps=12 ..."""

TABLE_MD, TABLE_JSON = "robustness.md", "robustness.json"


@dataclass
class RobustnessConfig:
    """`geoloc robustness`'s own keys (schema/robustness: geoloc/conf/robustness.yaml); dataset*, cross: split_args."""

    ckpt: str = MISSING
    out: str | None = None
    overwrite: bool = False
    fovs: list[float] = field(default_factory=lambda: [360.0, 180.0, 90.0, 70.0])
    heading_steps: int = 12
    distractors: int = 1000
    distractor_split: str = "train"
    device: str = "auto"
    num_workers: int = 0
    progress: bool = False

    def __post_init__(self):
        check_fovs(self.fovs)
        if self.heading_steps < 1 or self.distractors < 0:
            raise ValueError(f"heading_steps must be >= 1 and distractors >= 0, got {self.heading_steps} and "
                             f"{self.distractors}")


def split_args(args: list[str]) -> tuple[list[str], list[str], list[list[str]]]:
    """(robustness.yaml's overrides, the dataset ones, the cross rows'): dataset*, cross= go to evaluate.py as given."""
    own, dataset, cross = [], [], [["dataset=vigor"]]
    for arg in args:
        key, _, value = arg.partition("=")
        if key.lstrip("+~").split(".")[0] == "dataset":
            dataset.append(arg)
        elif key == "cross":
            cross = [] if value.strip() in ("", "none", "null") else [row.split() for row in value.split(";")]
        else:
            own.append(arg)
    return own, dataset, cross


def default_out(ckpt: str) -> Path:
    path = Path(ckpt)
    return path.parent / f"robustness_{path.stem}"


def robustness(args: list[str]) -> dict:
    """Compute and write the table; returns its JSON."""
    own, dataset, cross = split_args(args)
    cfg = compose_checked("robustness", RobustnessConfig, own, "robustness")
    out = Path(cfg.out) if cfg.out else default_out(cfg.ckpt)
    refuse_out_that_is_no_folder(out, [TABLE_MD, TABLE_JSON], "robustness")
    refuse_taken([out / TABLE_MD, out / TABLE_JSON], cfg.overwrite)
    if not Path(cfg.ckpt).is_file():
        raise ConfigError(f"ckpt={cfg.ckpt} is not a file: give a checkpoint written by train.py (best.pt)")
    plan = Plan(fovs=list(cfg.fovs), heading_steps=cfg.heading_steps, distractors=cfg.distractors,
                distractor_split=cfg.distractor_split, dataset=dataset, cross=cross)
    start = time.perf_counter()
    rows, notes = evaluate_conditions(cfg.ckpt, plan, lambda overrides: evaluate_config(
        cfg.ckpt, overrides, cfg.device, cfg.num_workers, cfg.progress))
    seconds = time.perf_counter() - start
    out.mkdir(parents=True, exist_ok=True)
    table, record = markdown(rows, plan, cfg.ckpt, seconds, notes), as_json(rows, plan, cfg.ckpt, seconds, notes)
    write_whole(out / TABLE_JSON, json.dumps(record, indent=2) + "\n", cfg.overwrite)
    write_whole(out / TABLE_MD, table, cfg.overwrite)
    print(f"\n{table}\nwritten: {out / TABLE_MD}  {out / TABLE_JSON}")
    return record


def main(args: list[str]) -> int:
    robustness(args)
    return 0
