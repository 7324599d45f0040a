"""Retrieval confidence: P(the top-1 reference is the query's positive), fitted when a gallery is saved.

The rule (docs/confidence.md): the labelled queries are `dataset.calibration_holdout` train queries spread evenly
over the split (datasets.holdout_rows), which training never saw (datasets.calibration_data). Each is scored
against the gallery's references plus its own positive where the gallery lacks it (a one-to-one split's train
tiles are not in the test gallery), so the answers it fits face the gallery's distractors. "Right" is the scorer's
rank rule: no reference strictly above the positive (R@1's hit). The features are the top-1 score and its margin
over the second (calibration.py). The calibrator holds for the condition it was fitted in: the heading given (the
held-out queries are encoded at their known heading) at the checkpoint's field of view.

A checkpoint with a refiner adds a second target, "within_5m": P(the refined position is within 5 m of the truth,
given that the tile holds the camera). Each held-out query is refined in its positive tile (the fine-grained
protocol, at the refiner's test headings); the feature is the log-odds of the refiner's probability mass within
5 m of its answer (Refinement.mass_within). It is the refinement's own confidence: an end-to-end answer is within
5 m only if its tile is right too, which the top-1 confidence gives.

calibration.json (saved with the gallery) holds {"calibrated": true, "targets": {"top1": Calibrator, ...}} or
{"calibrated": false, "why": ...}; "calibrated" is the top-1 confidence's. A refiner's "within_5m" is one more
entry of "targets" when it was fitted, else "refiner_why" says why not. A gallery built across jobs has no top-1
calibrator (ACROSS_JOBS says why) and keeps the refiner's, which shard 0's job fits as a one-job save would.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from geoloc.data.relevance import Relevance
from geoloc.eval.calibration import (RETRIEVAL_FEATURES, Calibrator, coverage_accuracy, expected_calibration_error,
                                     fit_calibrator, retrieval_features)
from geoloc.eval.candidates import rank_candidates
from geoloc.eval.search_index import GalleryIndex
from geoloc.eval.scoring import rank

TOP1 = "top1"
WITHIN_5M = "within_5m"
REFINE_FEATURES = ("mass_5m_logit",)
TARGET_FEATURES = {TOP1: RETRIEVAL_FEATURES, WITHIN_5M: REFINE_FEATURES}  # the features computed for each target
MASS_CLIP = 1e-6  # a mass of exactly 0 or 1 has infinite log-odds
NO_HOLDOUT = ("no labelled queries were kept out of training (the checkpoint was trained with "
              "dataset.calibration_holdout=0): train with dataset.calibration_holdout=N (e.g. a quarter of the train "
              "queries) and save the gallery again to have a calibrated confidence")
ACROSS_JOBS = ("the top-1 confidence is fitted against the whole gallery's references, which no shard job holds, and "
               "the merge does not refit it: a gallery merged from shards is uncalibrated for the top-1 tile (a "
               "refiner's confidence, fitted without the gallery, is kept from shard 0). Save the gallery in one job "
               "(python evaluate.py ckpt=CKPT gallery.save=DIR) for a calibrated top-1 confidence")


def top1_answers(query: torch.Tensor, reference: torch.Tensor, positives) -> tuple[np.ndarray, np.ndarray]:
    """(features (Q, 2), right (Q,) bool) of exact retrieval: query Q×D against reference N×D, query i's positive
    reference positives[i]."""
    relevance = Relevance.from_positives(positives, reference.shape[0])
    found = rank(query, reference, relevance, top=2)
    return retrieval_features(found.top_scores.numpy()), (found.ranks == 0).numpy()


def index_answers(index: GalleryIndex, query: torch.Tensor, positives) -> tuple[np.ndarray, np.ndarray]:
    """top1_answers from a gallery index: its stored vectors when exact, else its top-2 lists."""
    if index.kind == "flat":
        return top1_answers(query, index.vectors(), positives)
    scores, rows = index.search(query, min(2, len(index)))
    found = rank_candidates(scores, rows, Relevance.from_positives(positives, len(index)))
    return retrieval_features(found.top_scores.numpy()), (found.ranks == 0).numpy()


def with_positives(reference: torch.Tensor, paths: list, held_reference: torch.Tensor, held_paths: list,
                   held_positives) -> tuple[torch.Tensor, np.ndarray]:
    """(the gallery's references plus each held-out positive it lacks, the held-out queries' rows in it). A
    held-out positive found in the gallery (the same file) keeps its gallery row."""
    row_of = {Path(p): i for i, p in enumerate(paths)}
    extra, rows = [], []
    for j in np.asarray(held_positives):
        path = Path(held_paths[j])
        if path not in row_of:
            row_of[path] = len(paths) + len(extra)
            extra.append(int(j))
        rows.append(row_of[path])
    added = held_reference[torch.as_tensor(extra, dtype=torch.long)].to(reference.device)
    return torch.cat([reference, added]), np.asarray(rows)


def fit_top1(query: torch.Tensor, reference: torch.Tensor, positives, fov: float, rule: str) -> dict:
    """calibration.json's record for held-out queries scored against `reference` (with_positives)."""
    features, right = top1_answers(query, reference, positives)
    if right.all() or not right.any():
        return uncalibrated(f"the {len(right)} held-out queries were all {'right' if right.all() else 'wrong'}: "
                            "no answer to learn the confidence from; keep more queries out of training")
    calibrator = fit_calibrator(features, right, TOP1, condition={"heading": "given", "fov": float(fov)},
                                rule=rule)
    return {"calibrated": True, "targets": {TOP1: calibrator.to_json()}}


def uncalibrated(why: str) -> dict:
    return {"calibrated": False, "why": why}


def refine_features(mass) -> np.ndarray:
    """(Q,) probability masses within 5 m -> (Q, 1) their log-odds: Platt scaling's score."""
    m = np.clip(np.asarray(mass, np.float64), MASS_CLIP, 1.0 - MASS_CLIP)
    return np.log(m / (1.0 - m))[:, None]


def fit_within(mass, error_m, radius_m: float, condition: dict, rule: str) -> Calibrator | str:
    """The "within_5m" calibrator of held-out queries refined in their positive tiles ((Q,) masses and metre
    errors), or why there is none."""
    right = np.asarray(error_m) <= radius_m
    if right.all() or not right.any():
        return (f"the {len(right)} held-out queries were all {'within' if right.all() else 'beyond'} {radius_m:g} m: "
                "no answer to learn the refiner's confidence from; keep more queries out of training")
    return fit_calibrator(refine_features(mass), right, WITHIN_5M, REFINE_FEATURES, condition, rule)


def with_refiner(record: dict, fitted: Calibrator | str) -> dict:
    """calibration.json's record with the refiner's target added, or the reason it has none."""
    if isinstance(fitted, str):
        return {**record, "refiner_why": fitted}
    return {**record, "targets": {**record.get("targets", {}), WITHIN_5M: fitted.to_json()}}


def check_record(record) -> dict:
    """A calibration.json record, checked against what the code computes before anything is scored with it: a
    JSON object whose "calibrated" is a bool, whose "targets" (where present) map each target geoloc computes to a
    calibrator of that target's features (TARGET_FEATURES), the top-1 among them when "calibrated". A ValueError
    says what is wrong, as a phrase that follows the file's name."""
    if not isinstance(record, dict) or not isinstance(record.get("calibrated"), bool):
        raise ValueError('holds no calibration record ({"calibrated": true, "targets": {...}} or {"calibrated": '
                         'false, "why": ...})')
    targets = record.get("targets", {})
    if not isinstance(targets, dict):
        raise ValueError(f'holds "targets" as a JSON {type(targets).__name__}, not an object of calibrators by '
                         f"target ({', '.join(TARGET_FEATURES)})")
    if record["calibrated"] and TOP1 not in targets:
        raise ValueError(f'says "calibrated": true but holds no {TOP1!r} target')
    for target, entry in targets.items():
        if target not in TARGET_FEATURES:
            raise ValueError(f"holds a target {target!r}, which geoloc does not compute ({', '.join(TARGET_FEATURES)})")
        calibrator = Calibrator.from_json(entry, f"holds a target {target!r} that")
        if calibrator.target != target or calibrator.features != TARGET_FEATURES[target]:
            raise ValueError(f"holds a target {target!r} fitted as {calibrator.target!r} on the features "
                             f"{list(calibrator.features)}, where geoloc computes {list(TARGET_FEATURES[target])} "
                             "for it")
    return record


def across_jobs(record: dict | None) -> dict:
    """calibration.json of a gallery built across jobs (a shard's, or the merge of the shards whose shard 0 holds
    `record`): the top-1 confidence uncalibrated (ACROSS_JOBS), the refiner's as `record` holds it, or why not."""
    merged = uncalibrated(ACROSS_JOBS)
    within = calibrators(record).get(WITHIN_5M)
    if within is not None:
        return with_refiner(merged, within)
    return {**merged, "refiner_why": record["refiner_why"]} if record and "refiner_why" in record else merged


def calibrators(record: dict | None) -> dict[str, Calibrator]:
    """{target: Calibrator} of a calibration.json record (None: a gallery saved without one: none). The top-1
    target is there only when the record is "calibrated"; a refiner's target whenever it was fitted."""
    if not record:
        return {}
    return {target: Calibrator.from_json(entry, f"calibration.json target {target!r}")
            for target, entry in record.get("targets", {}).items()
            if target != TOP1 or record.get("calibrated")}


def refiner_calibrator(record: dict | None, condition: dict) -> Calibrator | str:
    """The record's "within_5m" calibrator where it was fitted for the refiner and condition that will use it
    (`condition`: refine_confidence.refiner_condition of that refiner), else why that refiner has no confidence. A
    gallery's retrieval weights do not name its refiner, so a gallery may meet another refiner than the one its
    calibrator was fitted for; its top-1 confidence stays valid."""
    fitted = calibrators(record).get(WITHIN_5M)
    if fitted is None:
        return (record or {}).get("refiner_why", "the gallery was saved without the refiner's calibration")
    differs = [f"{key} {fitted.condition.get(key)!r} (calibration) vs {value!r} (this refiner)"
               for key, value in condition.items() if fitted.condition.get(key) != value]
    if differs:
        return (f"its calibration was fitted for another refiner or condition ({'; '.join(differs)}): the gallery "
                "was saved with another checkpoint's refiner, or by an earlier geoloc that did not record the "
                "refiner's weights. Save the gallery again with this checkpoint (python evaluate.py ckpt=CKPT "
                "gallery.save=DIR) for its refiner's confidence")
    return fitted


def confidence_report(calibrator: Calibrator, features: np.ndarray, right: np.ndarray,
                      figure: Path | None = None) -> dict:
    """{"ece_<target>": ...} of the scored answers (ece_top1, ece_within_5m); with `figure`, their reliability and
    coverage-accuracy curves."""
    probability = calibrator.probability(features)
    ece = expected_calibration_error(probability, right)
    if figure is not None:
        from geoloc.eval.plots import confidence_figure

        confidence_figure(figure, probability, right, ece, *coverage_accuracy(probability, right))
    return {f"ece_{calibrator.target}": ece}
