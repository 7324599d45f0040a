"""The refiner's confidence in evaluate.py's gallery path: P(the refined position is within 5 m | the tile holds the
camera), fitted on the held-out train queries when a gallery is saved, scored on the evaluated queries.

Both sides refine each query in its positive tile (refine.fine_answers: the refiner's mass within 5 m of its
answer and the answer's metre error) at the refiner's test headings; confidence.py holds the fit and the record.
The scored side also reports the fine-grained metres (`fine_*`), so a gallery evaluation of a checkpoint with a
refiner states the refiner's accuracy beside its calibration.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geoloc.engine import distributed as dist
from geoloc.eval.calibration import Calibrator
from geoloc.eval.fine_error import fine_summary
from geoloc.tasks.crossview.confidence import (NO_HOLDOUT, WITHIN_5M, calibrators, confidence_report, fit_within,
                                               refine_features)
from geoloc.tasks.crossview.datasets import holdout_rule
from geoloc.tasks.crossview.refine import RADIUS_M, fine_answers, labels_of

NO_SCALE = "the split's tiles have no metres per pixel, so the refiner's error has no metres to calibrate"


def refine_answers(task, split, maps: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """((Q,) masses within 5 m, (Q,) metre errors) of the split's queries refined in their positive tiles, from
    the refiner's maps in `maps` ("refine_query", "refine_reference": gallery.encode_split(refine=True)); None
    without a refiner or without a metre scale."""
    if task.refiner is None or split.reference_metres_per_px is None:
        return None
    return fine_answers(task.refiner, split, task.refine_candidates(), maps["refine_query"], maps["refine_reference"])


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
    split = held_out.split
    condition = {"tile": "holds the camera", "orientation_noise_deg": float(task.refine.orientation_noise_deg),
                 "radius_m": RADIUS_M}
    rule = holdout_rule(split, "each refined in its positive tile")
    return fit_within(*answers, RADIUS_M, condition, rule)


def scored_within(record: dict | None, task, split, maps: dict, run_dir: Path | None) -> dict:
    """The fine_* metres of the split's queries refined in their positive tiles (the refiner's `maps`, as in
    refine_answers) and, under a gallery calibrated for the refiner, `ece_within_5m` and
    run_dir/confidence_within_5m.png; {} without a refiner."""
    answers = refine_answers(task, split, maps)
    if answers is None:
        return {}
    mass, error = answers
    out = {**fine_summary(error), **labels_of(split)}
    calibrator = calibrators(record).get(WITHIN_5M)
    if calibrator is not None:
        figure = Path(run_dir) / f"confidence_{WITHIN_5M}.png" if run_dir is not None and dist.is_main() else None
        out.update(confidence_report(calibrator, refine_features(mass), error <= RADIUS_M, figure))
    return out
