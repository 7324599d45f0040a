"""One checkpoint under every test condition the field reports: field of view, known or unknown heading, a gallery
padded with distractor tiles of other places, and another dataset. Each cell is evaluate.py's own path: its config
composed from geoloc/conf/evaluate.yaml with the condition's overrides (`dataset.fov=90 dataset.random_heading=true ...`),
config.parse_evaluation, then run.score; nothing here ranks or scores.

Conditions, in table order:
- for the gallery as it is, then padded with `distractors` tiles (University-160k style: references of other
  places, relevant to no query; tiles of the distractor split that the evaluated gallery holds are left out, and
  where that leaves none, as in VIGOR same-area, so are the padded rows, with a note saying why), each FoV in
  `fovs`, the heading known (the view at north) and unknown (searched over `heading_steps` candidate headings,
  360·k/K, docs/heading.md);
- a cross-dataset row per `cross` entry (evaluate.py overrides, e.g. ["dataset=vigor"]): that dataset's evaluation
  split at FoV 360, heading known.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from geoloc.config import ConfigError
from geoloc.engine import checkpoint as ckpt_io
from geoloc.tasks.crossview.crossview_config import parse_evaluation
from geoloc.tasks.crossview.datasets import eval_sets, padded, read_split
from geoloc.tasks.crossview.crossview_run import restored_task, score, stored_config

KEYS = ("R@1", "R@5", "R@1%")  # the recall columns
HEADING_KEY = "heading_median_deg"


@dataclass(frozen=True)
class Condition:
    """One row: evaluate.py's overrides for it (the dataset and test condition), and the gallery's padding."""

    overrides: tuple
    fov: float
    unknown_heading: bool
    distractors: int = 0
    cross: bool = False

    @property
    def heading(self) -> str:
        return "unknown" if self.unknown_heading else "known"


@dataclass
class Plan:
    """What `robustness` evaluates: see the module docstring. `dataset`: evaluate.py's overrides naming the data of
    the main rows (empty: the checkpoint's own dataset and split); `distractor_split`: the split of the same dataset
    whose references pad the gallery (the first `distractors` of those not in the evaluated gallery, in the reader's
    order)."""

    fovs: list[float] = field(default_factory=lambda: [360.0, 180.0, 90.0, 70.0])
    heading_steps: int = 12
    distractors: int = 1000
    distractor_split: str = "train"
    dataset: list[str] = field(default_factory=list)
    cross: list[list[str]] = field(default_factory=list)

    def conditions(self) -> list[Condition]:
        padding = [0] + ([self.distractors] if self.distractors > 0 else [])
        rows = [Condition((*self.dataset, *test_condition(fov, unknown, self.heading_steps)), fov, unknown, count)
                for count in padding for fov in self.fovs for unknown in (False, True)]
        for cross in self.cross:
            rows.append(Condition((*cross, *test_condition(360.0, False, self.heading_steps)), 360.0, False,
                                  cross=True))
        return rows


def test_condition(fov: float, unknown_heading: bool, heading_steps: int) -> tuple[str, ...]:
    """evaluate.py's overrides for one field of view and heading."""
    return (f"dataset.fov={float(fov)}", f"dataset.random_heading={str(unknown_heading).lower()}",
            f"dataset.heading_steps={heading_steps}")


def evaluate_conditions(ckpt: str, plan: Plan, compose, on_row=None) -> tuple[list[dict], list[str]]:
    """([{"condition": Condition, "split": name, "distractors": tiles added, "metrics": evaluate.py's metrics}] for
    each of plan.conditions(), notes on the padding for the table). The network is built once from `ckpt`.
    compose(overrides) gives evaluate.py's config of a condition (the app composes it with Hydra); on_row(row) is
    called as each row is done. Every condition's config and the padded gallery are checked before the first row is
    evaluated; where no tile of plan.distractor_split lies outside the evaluated gallery, the padded rows are left
    out and a note says why."""
    state = ckpt_io.load(ckpt)
    stored = stored_config(state)
    conditions = plan.conditions()
    runs = [parse_evaluation(compose(c.overrides), stored) for c in conditions]
    notes, gallery, distractors = [], None, []
    first = next((run for c, run in zip(conditions, runs) if c.distractors), None)
    if first is not None:  # every padded row shares the main rows' data: one padded gallery for all
        split = read_split(first.data, first.reader, first.data.split)
        distractors, note = distractor_tiles(first, split, plan.distractor_split, plan.distractors)
        notes += [note] if note else []
        if distractors:
            gallery = padded(split, distractors)
        else:
            conditions, runs = zip(*[(c, run) for c, run in zip(conditions, runs) if not c.distractors])
    task = restored_task(state, ckpt, stored)
    rows = []
    for condition, run in zip(conditions, runs):
        eval_data = eval_sets(run.data, gallery) if condition.distractors else None
        metrics = score(run, task, eval_data)
        row = {"condition": condition, "split": eval_data.split.name if eval_data else _split_name(run),
               "distractors": len(distractors) if condition.distractors else 0, "metrics": metrics}
        rows.append(row)
        if on_row is not None:
            on_row(row)
    return rows, notes


def distractor_tiles(run, split, distractor_split: str, count: int) -> tuple[list[Path], str | None]:
    """(the first `count` references of `distractor_split` of the evaluated dataset that are not in `split`'s
    gallery: other places; a note on the tiles left out, None when none were). A dataset whose splits share their
    tiles (VIGOR same-area: every split's gallery is every tile of the four cities) gives fewer, or none."""
    if distractor_split == run.data.split:
        raise ConfigError(f"distractor_split={distractor_split} is the evaluated split itself: its tiles are the "
                          "queries' own places; pad with another split (train)")
    source = read_split(run.data, run.reader, distractor_split)
    gallery = set(split.references)
    others = [path for path in source.references if path not in gallery]
    shared = len(source.references) - len(others)
    if not shared:
        return others[:count], None
    if not others:
        return [], (f"No padded rows: every tile of distractor_split={distractor_split} ({shared}) is in the "
                    f"evaluated gallery of {split.name}, so none shows another place (VIGOR same-area splits share "
                    "the four cities' tiles). To pad, evaluate a split whose gallery leaves tiles out "
                    "(dataset.setting=cross_area) or name another distractor_split.")
    return others[:count], (f"The {shared} tiles of distractor_split={distractor_split} that are in the evaluated "
                            f"gallery of {split.name} are not distractors: the padding is drawn from its "
                            f"{len(others)} others.")


def _split_name(run) -> str:
    return f"{run.data.name}/{run.data.split}"


def cell(metrics: dict, key: str) -> str:
    value = metrics.get(key)
    if value is None:
        return "-"
    return f"{value:.1f}" if key == HEADING_KEY else f"{100 * value:.2f}"


def markdown(rows: list[dict], plan: Plan, ckpt: str, seconds: float, notes: list[str] = ()) -> str:
    """The table: recall in %, the median heading error in degrees (unknown heading only); then the notes."""
    lines = [f"Robustness of `{ckpt}` ({seconds:.0f} s). Recall in %; unknown heading: searched over "
             f"{plan.heading_steps} candidate headings (every {360 / plan.heading_steps:g}°), each query at a "
             "fixed pseudo-random true heading (`views.eval_heading`); the heading error is the median over queries "
             "of the best candidate's circular error to it.", "",
             "| split | gallery | FoV | heading | " + " | ".join(KEYS) + " | median heading error (°) |",
             "|---|---|---|---|" + "---|" * len(KEYS) + "---|"]
    for row in rows:
        c, m = row["condition"], row["metrics"]
        gallery = f"{m.get('num_references', '?')} tiles" + (f" ({row['distractors']} distractors)"
                                                             if row["distractors"] else "")
        split = row["split"].split(" + ")[0] + (" (cross-dataset)" if c.cross else "")
        lines.append(f"| {split} | {gallery} | {c.fov:g} | {c.heading} | "
                     + " | ".join(cell(m, k) for k in KEYS) + f" | {cell(m, HEADING_KEY)} |")
    lines += [f"\n{note}" for note in notes]
    return "\n".join(lines) + "\n"


def as_json(rows: list[dict], plan: Plan, ckpt: str, seconds: float, notes: list[str] = ()) -> dict:
    return {"ckpt": str(ckpt), "seconds": round(seconds, 1), "heading_steps": plan.heading_steps,
            "distractor_split": plan.distractor_split, "notes": list(notes),
            "rows": [{"split": r["split"], "fov": r["condition"].fov, "heading": r["condition"].heading,
                      "distractors": r["distractors"], "cross_dataset": r["condition"].cross,
                      "overrides": list(r["condition"].overrides), "metrics": r["metrics"]} for r in rows]}
