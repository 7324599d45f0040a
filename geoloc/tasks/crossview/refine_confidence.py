"""The refiner's confidence in evaluate.py's gallery path: P(the refined position is within 5 m | the tile holds the
camera), fitted on the held-out train queries when a gallery is saved, scored on the evaluated queries.

Both sides refine each query in every tile that holds it (refine.whole_tile_answers: the refiner's mass within 5 m
of its answer and the answer's metre error), so the truths cover the whole tile as a real query's do in its best
tile, at the refiner's test headings; confidence.py holds the fit and the record. The scored side also reports the
refiner's metrics as the plain evaluation does (refine.fine_metrics: `fine_*`, `whole_tile_*`, `fine_heading_*`,
`e2e_*` where they apply), so a gallery evaluation of a checkpoint with a refiner states the refiner's accuracy
beside its calibration.
"""

from __future__ import annotations

import warnings
from pathlib import Path

from geoloc.engine import distributed as dist
from geoloc.engine.checkpoint import weights_fingerprint
from geoloc.eval.calibration import Calibrator
from geoloc.gallery.confidence import (NO_HOLDOUT, WITHIN_5M, confidence_report, fit_within,
                                               refine_features, refiner_calibrator)
from geoloc.tasks.crossview.datasets import holdout_rule
from geoloc.tasks.crossview.refine import RADIUS_M, RefineConfig, TileAnswers, refiner_metrics, whole_tile_answers

NO_SCALE = "the split's tiles have no metres per pixel, so the refiner's error has no metres to calibrate"


def refine_answers(task, split, maps: dict) -> TileAnswers | None:
    """The split's queries refined in every tile that holds them, from the refiner's maps in `maps`
    ("refine_query", "refine_reference": gallery.encode_split(refine=True)); None without a refiner or without a
    metre scale."""
    if task.refiner is None or split.reference_metres_per_px is None:
        return None
    return whole_tile_answers(task.refiner, task.refine, split, task.refine_candidates(), maps["refine_query"],
                              maps["refine_reference"])


def fitted_within(task, held_out, held: dict | None) -> Calibrator | str | None:
    """The "within_5m" calibrator of the held-out queries (`held`: their encode_split(refine=True)), why there is
    none, or None without a refiner."""
    if task.refiner is None:
        return None
    if held_out is None:
        return NO_HOLDOUT
    answers = refine_answers(task, held_out.split, held)
    if answers is None:
        return NO_SCALE
    rule = holdout_rule(held_out.split, f"each refined in every tile that holds it ({len(answers.mass)} answers)")
    return fit_within(answers.mass, answers.error_m, RADIUS_M, refiner_condition(task.refiner, task.refine), rule)


def refiner_condition(refiner, refine: RefineConfig) -> dict:
    """What a "within_5m" calibrator holds for, recorded as its condition when it is fitted and compared before it
    is used: the refiner's own weights (their fingerprint: two refiners trained from one retrieval run share the
    gallery's retrieval weights, not these) and the RefineConfig keys that shape its test answers, beside the tile
    and the radius it counts."""
    condition = {"tile": "holds the camera, anywhere in it", "radius_m": RADIUS_M,
                 "orientation_noise_deg": float(refine.orientation_noise_deg), "size": int(refine.size),
                 "query_extent_m": float(refine.query_extent_m), "refiner_fingerprint": weights_fingerprint(refiner)}
    if refine.peak_smoothing:  # recorded where set, so the calibrations of galleries saved before it stay valid
        condition["peak_smoothing"] = float(refine.peak_smoothing)
    if refine.margin:  # the same: a refiner reading no margin keeps its condition
        condition["margin"] = float(refine.margin)
    return condition


def scored_refiner(record: dict | None, task, split, maps: dict, top1, run_dir: Path | None) -> dict:
    """The refiner's metrics of the split's queries, as the plain evaluation reports them (refine.refiner_metrics,
    from the refiner's `maps` and the queries' "refine_heading" of gallery.encode_split(refine=True); `top1()`: each
    query's top-1 tile in the gallery) and, under a gallery calibrated for this refiner (refiner_calibrator),
    `ece_within_5m` over every tile that holds a query and run_dir/confidence_within_5m.png; {} without a
    refiner."""
    if task.refiner is None:
        return {}
    answers = refine_answers(task, split, maps)
    out = refiner_metrics(task, split, maps, top1, answers)
    if answers is None:
        return out
    calibrator = refiner_calibrator(record, refiner_condition(task.refiner, task.refine))
    if isinstance(calibrator, str):
        if record and WITHIN_5M in record.get("targets", {}):  # fitted, but for another refiner or condition
            warnings.warn(f"no ece_within_5m: {calibrator}")
    else:
        figure = Path(run_dir) / f"confidence_{WITHIN_5M}.png" if run_dir is not None and dist.is_main() else None
        out.update(confidence_report(calibrator, refine_features(answers.mass), answers.error_m <= RADIUS_M, figure))
    return out
