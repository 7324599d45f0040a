"""Retrieval confidence on the cross-view task: the held-out train queries (never trained on), the fit against the
gallery plus their own positives (brute force), calibration.json saved with the gallery and read back, and the
ECE evaluate.py reports."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from geoloc.config import ConfigError
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.calibration import expected_calibration_error, fit_calibrator
from geoloc.tasks.crossview import gallery_build as crossview_gallery
from geoloc.gallery.confidence import NO_HOLDOUT, calibrators, with_positives
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.datasets import EvalData, calibration_data, holdout_rows, read_split
from geoloc.gallery.index_settings import GalleryConfig
from geoloc.gallery.folder import open_gallery
from helpers.gallery_runs import META, pairs_split

from conftest import write_cvusa


def test_train_queries_spread_over_the_split_are_held_out_of_training_and_fit_the_confidence(tmp_path):
    root = write_cvusa(tmp_path / "cvusa", n_train=10, n_val=3)
    reader = {"name": "cvusa", "module": None}
    full = read_split(CrossViewDataConfig(name="cvusa", root=str(root)), reader, "train")
    cfg = CrossViewDataConfig(name="cvusa", root=str(root), calibration_holdout=4)
    trained = read_split(cfg, reader, "train")
    held = calibration_data(cfg, reader).split
    held_rows, trained_rows = [1, 4, 6, 9], [0, 2, 3, 5, 7, 8]  # floor((i + 1) 10 / 4) - 1
    assert trained.queries == [full.queries[i] for i in trained_rows]
    assert trained.references == [full.references[i] for i in trained_rows]
    assert held.queries == [full.queries[i] for i in held_rows]
    assert held.references == [full.references[i] for i in held_rows]
    assert held.one_to_one and trained.one_to_one and not set(held.queries) & set(trained.queries)
    # a split listed city by city (VIGOR: 4 cities of 64 panoramas) gives each city its share, not the last city
    rows = holdout_rows(256, 64)
    assert len(set(rows.tolist())) == 64 and rows[-1] == 255
    assert np.bincount(rows // 64).tolist() == [16, 16, 16, 16]
    assert holdout_rows(7, 7).tolist() == list(range(7))
    assert calibration_data(CrossViewDataConfig(name="cvusa", root=str(root)), reader) is None
    with pytest.raises(ConfigError, match="calibration_holdout=10 keeps every one of the 10 train queries"):
        read_split(CrossViewDataConfig(name="cvusa", root=str(root), calibration_holdout=10), reader, "train")
    with pytest.raises(ValueError, match="calibration_holdout must be >= 0"):
        CrossViewDataConfig(calibration_holdout=-1)


def test_with_positives_appends_only_the_positives_the_gallery_lacks():
    reference = torch.arange(6.0).reshape(3, 2)
    held = 10 + torch.arange(8.0).reshape(4, 2)
    gallery, rows = with_positives(reference, ["a", "b", "c"], held, ["x", "b", "y", "z"], [2, 1, 0, 2])
    assert rows.tolist() == [3, 1, 4, 3]  # y appended once, b found in the gallery, x appended
    assert torch.equal(gallery, torch.cat([reference, held[[2, 0]]]))


def unit(rng, n, d=8):
    x = rng.normal(size=(n, d))
    return torch.tensor(x / np.linalg.norm(x, axis=1, keepdims=True), dtype=torch.float32)


def brute_answers(query, reference, positives):
    """(features, right) by loops: top-1 score, top-1 minus top-2, and no reference strictly above the positive."""
    features, right = [], []
    for i, q in enumerate(query):
        scores = [float(q @ r) for r in reference]
        best = sorted(scores, reverse=True)
        features.append([best[0], best[0] - best[1]])
        right.append(not any(s > scores[positives[i]] for j, s in enumerate(scores) if j != positives[i]))
    return np.array(features), np.array(right)


@pytest.fixture
def descriptors():
    rng = np.random.default_rng(0)
    test_ref, held_ref = unit(rng, 40), unit(rng, 30)
    noisy = lambda ref, s: torch.nn.functional.normalize(ref + s * unit(rng, len(ref)), dim=1)  # noqa: E731
    return {"test": (noisy(test_ref, 0.9), test_ref), "held": (noisy(held_ref, 0.9), held_ref)}


def run_gallery(monkeypatch, tmp_path, descriptors, held: bool, **cfg):
    test, held_split = pairs_split(40), RetrievalSplit("held", "/data", [f"h{i}.jpg" for i in range(30)],
                                                       [f"hr{i}.jpg" for i in range(30)], np.arange(30))
    data = {"test": EvalData(test), "held": EvalData(held_split)}
    name = {id(v): k for k, v in data.items()}
    monkeypatch.setattr(crossview_gallery, "encode_split",
                        lambda task, engine, d, batch_size, sides=("query", "reference"), rows=None, refine=False:
                        dict(zip(("query", "reference"), descriptors[name[id(d)]])))
    engine = SimpleNamespace(device=torch.device("cpu"))
    # what evaluate reads of the task: its descriptor size, and no refiner
    task = SimpleNamespace(model_cfg=SimpleNamespace(dim=descriptors["test"][1].shape[1]), refiner=None)
    return crossview_gallery.evaluate(task, engine, data["test"], 4, GalleryConfig(**cfg), META,
                                      data["held"] if held else None, 360.0, tmp_path / "run")


def test_a_saved_gallery_holds_the_confidence_fitted_on_the_held_out_queries(monkeypatch, tmp_path, descriptors):
    (tmp_path / "run").mkdir()
    folder = tmp_path / "gallery"
    metrics = run_gallery(monkeypatch, tmp_path, descriptors, True, save=str(folder))
    record = json.loads((folder / "calibration.json").read_text())
    assert record["calibrated"] is True
    stored = calibrators(record)["top1"]
    held_query, held_ref = descriptors["held"]
    features, right = brute_answers(held_query, torch.cat([descriptors["test"][1], held_ref]), list(range(40, 70)))
    assert 0 < right.sum() < 30
    expect = fit_calibrator(features, right, "top1")
    assert stored.weights == pytest.approx(expect.weights, rel=1e-4)  # float32 scores against float64 loops
    assert stored.bias == pytest.approx(expect.bias, rel=1e-4)
    assert stored.condition == {"heading": "given", "fov": 360.0} and stored.fitted_on["answers"] == 30
    test_query, test_ref = descriptors["test"]
    features, right = brute_answers(test_query, test_ref, list(range(40)))
    ece = expected_calibration_error(stored.probability(features), right)
    assert metrics["ece_top1"] == pytest.approx(ece) and metrics["R@1"] == pytest.approx(right.mean())
    assert (tmp_path / "run" / "confidence.png").stat().st_size > 1000
    # the gallery read back reports the same ECE
    opened = open_gallery(folder, META["model_fingerprint"], META["ckpt"], split=pairs_split(40),
                          dataset=META["dataset"])
    assert opened.calibration == record
    loaded = run_gallery(monkeypatch, tmp_path, descriptors, False, load=str(folder))
    assert loaded["ece_top1"] == pytest.approx(ece)


def test_a_gallery_without_held_out_queries_says_it_is_uncalibrated(monkeypatch, tmp_path, descriptors):
    folder = tmp_path / "gallery"
    metrics = run_gallery(monkeypatch, tmp_path, descriptors, False, save=str(folder))
    assert json.loads((folder / "calibration.json").read_text()) == {"calibrated": False, "why": NO_HOLDOUT}
    assert "ece_top1" not in metrics and not (tmp_path / "run" / "confidence.png").exists()
    (folder / "calibration.json").write_text('{"calibrated": "yes"}')
    with pytest.raises(ConfigError, match="calibration.json holds no calibration record"):
        open_gallery(folder, META["model_fingerprint"], META["ckpt"])
