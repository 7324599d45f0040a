"""The refiner's confidence, P(within 5 m | the tile holds the camera): the mass and metre error of each query refined
in its positive tile (brute force over the lattice), the fit on the held-out queries saved with the gallery, and the
ECE and fine-grained metres evaluate.py reports from it."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.calibration import expected_calibration_error, fit_calibrator
from geoloc.models.refiners import Refinement
from geoloc.tasks.crossview import gallery_build as crossview_gallery
from geoloc.gallery.confidence import (NO_HOLDOUT, REFINE_FEATURES, TOP1, WITHIN_5M, calibrators,
                                               fit_within, refine_features, with_refiner)
from geoloc.tasks.crossview.datasets import EvalData
from geoloc.gallery.index_settings import GalleryConfig
from geoloc.tasks.crossview.refine import RefineConfig, whole_tile_answers
from geoloc.tasks.crossview.refine_confidence import refiner_condition
from helpers.gallery_runs import META

LATTICE = 17  # the fake refiner's map: 17 x 17 positions over the tile
SIDE_PX, METRES_PER_PX = 64, 0.5  # tiles of 32 m


class GaussianGuess(torch.nn.Module):
    """A refiner whose query map is its guess (row, col tile fractions) and a spread (metres): match gives the
    Gaussian of that spread around the guess on the lattice; the reference map is ignored. `version`: its one
    weight, which tells two of them apart (their fingerprint) without changing what they answer."""

    def __init__(self, version: float = 0.0):
        super().__init__()
        self.register_buffer("version", torch.tensor(version))

    def encode_query(self, images):
        return images

    def encode_reference(self, images):
        return images

    def match(self, query, reference, headings_deg):
        ys = torch.linspace(0, 1, LATTICE, dtype=torch.float64)
        d2 = ((ys[None, :, None] - query[:, 0, None, None]) ** 2 + (ys[None, None, :] - query[:, 1, None, None]) ** 2)
        spread = (query[:, 2] / (SIDE_PX * METRES_PER_PX))[:, None, None]  # metres -> tile fractions
        logits = (-0.5 * d2 / spread ** 2).flatten(1)
        log_prob = torch.log_softmax(logits, 1).reshape(-1, 1, LATTICE, LATTICE)
        return Refinement(log_prob.float(), torch.zeros(1))


def tile_split(n: int, seed: int, name: str) -> RetrievalSplit:
    """A one-to-one split of n tiles of 32 m, each query within 4 m of its tile's centre."""
    rng = np.random.default_rng(seed)
    return RetrievalSplit(name, "/data", [f"{name}q{i}.jpg" for i in range(n)], [f"{name}r{i}.jpg" for i in range(n)],
                          np.arange(n), reference_size_px=np.full((n, 2), SIDE_PX),
                          reference_metres_per_px=np.full(n, METRES_PER_PX),
                          query_tile_px=rng.uniform(24, SIDE_PX - 24, size=(n, 2)))  # guesses stay off the edges


def guesses(split: RetrievalSplit, seed: int) -> torch.Tensor:
    """(Q, 3) query maps: the truth moved by a random error of 0-10 m, and a spread of 1-6 m."""
    rng = np.random.default_rng(seed)
    truth = split.query_tile_px / SIDE_PX
    angle = rng.uniform(0, 2 * np.pi, split.num_queries)
    error_m = rng.uniform(0, 10, split.num_queries)
    moved = truth + (error_m / (SIDE_PX * METRES_PER_PX))[:, None] * np.stack([np.sin(angle), np.cos(angle)], 1)
    return torch.tensor(np.column_stack([moved.clip(0, 1), rng.uniform(1, 6, split.num_queries)]))


def brute_answers(split: RetrievalSplit, query: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(mass within 5 m of the estimate, metre error) by loops over the lattice."""
    out = GaussianGuess().match(query, None, torch.zeros(1))
    position = out.position().double().numpy()
    prob = out.position_log_prob.exp().double().numpy()
    step_m = SIDE_PX * METRES_PER_PX / (LATTICE - 1)
    masses, errors = [], []
    for i in range(split.num_queries):
        at = position[i] * (LATTICE - 1)
        masses.append(sum(prob[i, r, c] for r in range(LATTICE) for c in range(LATTICE)
                          if math.hypot((r - at[0]) * step_m, (c - at[1]) * step_m) <= 5.0))
        truth = split.query_tile_px[i] / SIDE_PX
        errors.append(math.hypot(*((position[i] - truth) * SIDE_PX * METRES_PER_PX)))
    return np.array(masses), np.array(errors)


def test_tile_answers_are_the_mass_within_5m_and_the_metre_error_in_the_positive_tile():
    split = tile_split(24, 0, "test")
    query = guesses(split, 1)
    mass, error, truth, positive = whole_tile_answers(GaussianGuess(), RefineConfig(), split, torch.zeros(1), query,
                                                      torch.zeros(24, 1))
    assert positive.all() and truth == pytest.approx(split.query_tile_px / SIDE_PX)  # one-to-one: no semi-positive
    expect_mass, expect_error = brute_answers(split, query)
    assert mass == pytest.approx(expect_mass, abs=1e-5)
    assert error == pytest.approx(expect_error, abs=1e-3)
    # the parabola through a Gaussian's log-probabilities finds its centre: the error is the guess's own
    guess_error = np.hypot(*((query[:, :2].numpy() - split.query_tile_px / SIDE_PX) * 32.0).T)
    assert error == pytest.approx(guess_error, abs=1e-3)
    assert 0.2 < (error <= 5).mean() < 0.8
    with pytest.raises(ValueError, match="no metres per pixel"):
        whole_tile_answers(GaussianGuess(), RefineConfig(), RetrievalSplit("plain", "/d", ["q"], ["r"], [0]),
                           torch.zeros(1), query[:1], torch.zeros(1, 1))


def test_the_within_5m_calibrator_is_a_logistic_fit_on_the_mass_log_odds():
    mass = np.array([0.05, 0.2, 0.5, 0.7, 0.9, 0.99, 1.0, 0.0])
    error = np.array([9.0, 6.0, 4.0, 7.0, 2.0, 1.0, 0.5, 20.0])
    fitted = fit_within(mass, error, 5.0, {"radius_m": 5.0}, "rule")
    expect = fit_calibrator(np.log(np.clip(mass, 1e-6, 1 - 1e-6) / (1 - np.clip(mass, 1e-6, 1 - 1e-6)))[:, None],
                            error <= 5, WITHIN_5M, REFINE_FEATURES)
    assert fitted.weights == pytest.approx(expect.weights) and fitted.bias == pytest.approx(expect.bias)
    assert fitted.weights[0] > 0  # more mass near the answer: more often within 5 m
    edge = math.log(1e-6 / (1 - 1e-6))  # a mass of 0 or 1 is clipped 1e-6 inside
    assert refine_features([0.0, 1.0]).ravel() == pytest.approx([edge, -edge])
    assert "all within 5 m" in fit_within(mass, np.zeros(8), 5.0, {}, "rule")
    # the record: the top-1 target only when "calibrated", the refiner's whenever fitted, else why not
    record = with_refiner({"calibrated": False, "why": "no holdout"}, fitted)
    assert set(calibrators(record)) == {WITHIN_5M}
    assert with_refiner({"calibrated": False, "why": "x"}, "none fitted")["refiner_why"] == "none fitted"


def refining_task(version: float = 0.0, **refine):
    return SimpleNamespace(model_cfg=SimpleNamespace(dim=8), refiner=GaussianGuess(version),
                           refine=RefineConfig(**refine), refine_candidates=lambda: torch.zeros(1))


def unit(rng, n, d=8):
    x = rng.normal(size=(n, d))
    return torch.tensor(x / np.linalg.norm(x, axis=1, keepdims=True), dtype=torch.float32)


SIDE = {"query": "query", "reference": "reference", "refine_query": "query", "refine_reference": "reference",
        "refine_heading": "query"}  # which side of encode_split gives each entry


def given_encoder(monkeypatch, given: dict):
    """gallery.encode_split replaced by the entries given for each EvalData (`given`: {id(data): {key: tensor}}):
    the refiner's only with refine=True, as from the same pass as the descriptors; `rows`: those references."""
    def encode_split(task, engine, data, batch_size, sides=("query", "reference"), rows=None, refine=False):
        out = {k: v for k, v in given[id(data)].items() if SIDE[k] in sides and (refine or k in SIDE.values())}
        return {k: v[list(rows)] if rows is not None and SIDE[k] == "reference" else v for k, v in out.items()}

    monkeypatch.setattr(crossview_gallery, "encode_split", encode_split)


def run_gallery(monkeypatch, tmp_path, held: bool, task=None, **cfg):
    """evaluate.py's gallery path (of `task`, default refining_task()) on 300 test and 200 held-out tiles,
    descriptors and refiner maps given."""
    rng = np.random.default_rng(5)
    splits = {"test": tile_split(300, 2, "test"), "held": tile_split(200, 3, "held")}
    data = {k: EvalData(v) for k, v in splits.items()}
    references = {k: unit(rng, v.num_queries) for k, v in splits.items()}
    descriptors = {k: (torch.nn.functional.normalize(r + 0.9 * unit(rng, len(r)), dim=1), r)  # noisy positives
                   for k, r in references.items()}
    maps = {"test": guesses(splits["test"], 4), "held": guesses(splits["held"], 6)}
    given_encoder(monkeypatch, {id(data[k]): {**dict(zip(("query", "reference"), descriptors[k])),
                                              "refine_query": maps[k], "refine_reference": torch.zeros(len(maps[k]), 1),
                                              "refine_heading": torch.zeros(len(maps[k]))} for k in data})
    engine = SimpleNamespace(device=torch.device("cpu"))
    metrics = crossview_gallery.evaluate(task or refining_task(), engine, data["test"], 4, GalleryConfig(**cfg), META,
                                         data["held"] if held else None, 360.0, tmp_path / "run")
    return metrics, splits, maps


def test_a_saved_gallery_holds_the_refiners_confidence_and_evaluation_scores_it(monkeypatch, tmp_path):
    (tmp_path / "run").mkdir()
    folder = tmp_path / "gallery"
    metrics, splits, maps = run_gallery(monkeypatch, tmp_path, True, save=str(folder))
    record = json.loads((folder / "calibration.json").read_text())
    stored = calibrators(record)[WITHIN_5M]
    held_mass, held_error = brute_answers(splits["held"], maps["held"])
    expect = fit_calibrator(refine_features(held_mass), held_error <= 5, WITHIN_5M, REFINE_FEATURES)
    assert stored.weights == pytest.approx(expect.weights, rel=1e-3) and stored.bias == pytest.approx(expect.bias,
                                                                                                       rel=1e-3)
    assert stored.fitted_on["answers"] == 200 and stored.condition["orientation_noise_deg"] == 0.0
    test_mass, test_error = brute_answers(splits["test"], maps["test"])
    ece = expected_calibration_error(stored.probability(refine_features(test_mass)), test_error <= 5)
    assert metrics["ece_within_5m"] == pytest.approx(ece, abs=1e-4)
    assert metrics["fine_median_m"] == pytest.approx(np.median(test_error), abs=1e-3)
    assert metrics["fine_within_5m"] == pytest.approx((test_error <= 5).mean())
    assert (tmp_path / "run" / "confidence_within_5m.png").stat().st_size > 1000
    # a refiner whose mass tracks its error is calibrated on other queries of the same kind
    assert ece < 0.1
    # read back with the gallery: the same ECE
    loaded, _, _ = run_gallery(monkeypatch, tmp_path, False, load=str(folder))
    assert loaded["ece_within_5m"] == pytest.approx(metrics["ece_within_5m"])
    assert TOP1 in record["targets"]  # the retrieval confidence beside it


def test_a_gallery_without_held_out_queries_has_no_refiner_confidence_and_still_reports_metres(monkeypatch,
                                                                                                tmp_path):
    folder = tmp_path / "gallery"
    metrics, _, _ = run_gallery(monkeypatch, tmp_path, False, save=str(folder))
    record = json.loads((folder / "calibration.json").read_text())
    assert record == {"calibrated": False, "why": NO_HOLDOUT, "refiner_why": NO_HOLDOUT}
    assert "ece_within_5m" not in metrics and "fine_median_m" in metrics
    assert not (tmp_path / "run" / "confidence_within_5m.png").exists()


def test_a_gallery_used_with_another_refiner_has_no_refiner_confidence_and_says_why(monkeypatch, tmp_path):
    """Two refiners trained from one retrieval run share its weights, hence the gallery's model fingerprint: an
    unknown-heading refiner served with a known-heading refiner's gallery gave the other's confidence (0.200 where
    its own gave 0.021), /health called it valid and evaluate.py gallery.load= reported the other's ECE."""
    from geoloc.apps.localize import Localizer

    (tmp_path / "run").mkdir()
    folder = tmp_path / "gallery"
    saved, _, _ = run_gallery(monkeypatch, tmp_path, True, save=str(folder))
    own, _, _ = run_gallery(monkeypatch, tmp_path, False, load=str(folder))
    assert own["ece_within_5m"] == pytest.approx(saved["ece_within_5m"])
    record = json.loads((folder / "calibration.json").read_text())
    for other, differs in ((refining_task(version=1.0), "refiner_fingerprint"),
                           (refining_task(orientation_noise_deg=180.0), "orientation_noise_deg")):
        with pytest.warns(UserWarning, match=rf"no ece_within_5m: its calibration was fitted for another refiner or "
                                             rf"condition \({differs} .* \(calibration\) vs .* \(this refiner\)"):
            foreign, _, _ = run_gallery(monkeypatch, tmp_path, False, task=other, load=str(folder))
        assert "ece_within_5m" not in foreign and "fine_median_m" in foreign
        assert foreign["R@1"] == own["R@1"] and foreign["ece_top1"] == own["ece_top1"]  # retrieval stays valid
        # the service: /health says why, and no answer carries the other refiner's confidence
        encoder = SimpleNamespace(device=torch.device("cpu"), data=SimpleNamespace(heading_steps=36),
                                  refiner=other.refiner, refine_config=other.refine,
                                  refiner_condition=refiner_condition(other.refiner, other.refine))
        health = Localizer(encoder, None, None, {"query_view": "panorama"}, calibration=record).calibration_info()
        assert health["calibrated"] is True and health[WITHIN_5M]["calibrated"] is False
        assert f"fitted for another refiner or condition ({differs} " in health[WITHIN_5M]["why"]
    encoder = SimpleNamespace(device=torch.device("cpu"), data=SimpleNamespace(heading_steps=36),
                              refiner=GaussianGuess(), refine_config=RefineConfig(),
                              refiner_condition=refiner_condition(GaussianGuess(), RefineConfig()))
    assert Localizer(encoder, None, None, {"query_view": "panorama"},
                     calibration=record).calibration_info()[WITHIN_5M]["calibrated"] is True


def vigor_like_split(seed: int = 0, queries: int = 120, side: int = 8) -> RetrievalSplit:
    """Queries over a side x side grid of 32 m tiles, each in its positive tile and in the neighbour east of it
    (a semi-positive holding its truth), with metre positions: every fine-grained key set applies."""
    rng = np.random.default_rng(seed)
    tiles = side * side
    # x, y: tiles 16 m apart west to east (each half over the next, as VIGOR's), 32 m apart north to south
    centre = np.stack(np.meshgrid(np.arange(side) * 16.0, np.arange(side) * -32.0), -1).reshape(-1, 2)
    positive = rng.integers(0, tiles - 1, queries)
    positive[(positive % side) == side - 1] -= 1  # an east neighbour for every positive
    px = np.column_stack([rng.uniform(8, 56, queries), rng.uniform(32, 64, queries)])  # the east half
    semi_px = np.column_stack([px[:, 0], px[:, 1] - 32.0])[:, None]  # in the east neighbour: 16 m = 32 px further west
    east_north = np.column_stack([(px[:, 1] / SIDE_PX - 0.5) * 32.0, (0.5 - px[:, 0] / SIDE_PX) * 32.0])
    return RetrievalSplit("vigor_like", "/data", [f"q{i}.jpg" for i in range(queries)],
                          [f"t{i}.png" for i in range(tiles)], positive, semi_positives=(positive + 1)[:, None],
                          query_xy=centre[positive] + east_north, reference_xy=centre,
                          reference_size_px=np.full((tiles, 2), SIDE_PX),
                          reference_metres_per_px=np.full(tiles, METRES_PER_PX), query_tile_px=px,
                          query_semi_tile_px=semi_px)


def test_the_gallery_path_reports_the_refiner_keys_and_values_of_the_plain_evaluation(monkeypatch, tmp_path):
    """The gallery path dropped fine_heading_* and e2e_*: an unknown-heading refiner's heading error was never
    reported from a gallery. Both paths now report refine.fine_metrics, on the same split the same numbers."""
    from geoloc.tasks.crossview.task import CrossViewTask
    from geoloc.tasks.crossview.validation import Retrieval

    split = vigor_like_split()
    rng = np.random.default_rng(1)
    reference = unit(rng, split.num_references)
    query = torch.nn.functional.normalize(reference[split.positives] + 0.5 * unit(rng, split.num_queries), dim=1)
    maps = guesses(split, 2)
    heading = torch.tensor(rng.uniform(0, 360, split.num_queries), dtype=torch.float32)
    task = SimpleNamespace(**vars(refining_task(orientation_noise_deg=180.0)), split=split, protocol=Retrieval())
    plain = CrossViewTask.validation_epoch_end(task, {
        "query": {"query": query, "refine_query": maps, "refine_heading": heading},
        "reference": {"reference": reference, "refine_reference": torch.zeros(len(reference), 1)}})
    assert {"fine_median_m", "whole_tile_median_m", "fine_heading_median_deg", "e2e_median_m"} <= set(plain)
    data = EvalData(split)
    given_encoder(monkeypatch, {id(data): {"query": query, "reference": reference, "refine_query": maps,
                                           "refine_reference": torch.zeros(len(reference), 1),
                                           "refine_heading": heading}})
    engine = SimpleNamespace(device=torch.device("cpu"))
    for cfg in ({"save": str(tmp_path / "gallery")}, {"load": str(tmp_path / "gallery")}):
        gallery = crossview_gallery.evaluate(task, engine, data, 4, GalleryConfig(**cfg), META)
        assert {k: gallery[k] for k in plain} == pytest.approx(plain), cfg
        assert 0 < gallery["R@1"] < 1  # some top-1 tiles are wrong: end to end is not the fine-grained protocol


def test_a_gallery_merged_from_shards_keeps_the_refiners_confidence_and_says_why_the_top1_is_uncalibrated(
        monkeypatch, tmp_path, capsys):
    """A gallery built across jobs had no calibration.json, /health said it was saved without one, and nothing
    warned at merge time. The refiner's calibration does not depend on the gallery: shard 0's job fits it and the
    merge keeps it; the top-1 confidence, fitted against the whole gallery, is uncalibrated and every place says
    why."""
    from geoloc.apps.localize import Localizer
    from geoloc.cli import main as geoloc
    from geoloc.gallery.confidence import ACROSS_JOBS

    (tmp_path / "run").mkdir()
    one_job = tmp_path / "one_job"
    run_gallery(monkeypatch, tmp_path, True, save=str(one_job))
    shards = [tmp_path / f"shard{i}" for i in range(2)]
    for i, folder in enumerate(shards):
        run_gallery(monkeypatch, tmp_path, True, save=str(folder), num_shards=2, shard_index=i)
    merged = tmp_path / "merged"
    assert geoloc(["gallery", "merge", *map(str, shards), f"out={merged}"]) == 0
    assert f"geoloc gallery: {merged} is uncalibrated for the top-1 tile: {ACROSS_JOBS}" in capsys.readouterr().err
    whole = json.loads((one_job / "calibration.json").read_text())
    record = json.loads((merged / "calibration.json").read_text())
    assert record == {"calibrated": False, "why": ACROSS_JOBS, "targets": {WITHIN_5M: whole["targets"][WITHIN_5M]}}
    scored = {f: run_gallery(monkeypatch, tmp_path, False, load=str(f))[0] for f in (one_job, merged)}
    assert scored[merged]["ece_within_5m"] == pytest.approx(scored[one_job]["ece_within_5m"])
    assert "ece_top1" in scored[one_job] and "ece_top1" not in scored[merged]
    encoder = SimpleNamespace(device=torch.device("cpu"), data=SimpleNamespace(heading_steps=36),
                              refiner=GaussianGuess(), refine_config=RefineConfig(),
                              refiner_condition=refiner_condition(GaussianGuess(), RefineConfig()))
    health = Localizer(encoder, None, None, {"query_view": "panorama"}, calibration=record).calibration_info()
    assert health["calibrated"] is False and health["why"] == ACROSS_JOBS and health[WITHIN_5M]["calibrated"]


def test_a_margin_is_part_of_the_calibrators_condition_only_where_set():
    """A refiner that reads its tiles with a margin answers differently from the same weights without one; a
    refiner without one keeps the condition its galleries were calibrated under."""
    plain = refiner_condition(GaussianGuess(), RefineConfig())
    wide = refiner_condition(GaussianGuess(), RefineConfig(margin=0.25))
    assert "margin" not in plain and wide == {**plain, "margin": 0.25}
    with pytest.raises(ValueError, match="refiner.margin"):
        RefineConfig(margin=0.6)
