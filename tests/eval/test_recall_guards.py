"""Recall never lies: non-finite descriptors raise, raw descriptors rank by cosine, a collapse scores 0, on every
backend and on the saved-gallery path (geoloc.eval.descriptors)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from geoloc.config import ConfigError
from geoloc.eval import GalleryIndex, recall_at_k
from geoloc.eval.descriptors import UNIT_TOLERANCE, unit_rows
from geoloc.eval.retrieval_metrics import index_metrics

from helpers.gallery_runs import gallery_evaluate, pairs_split
from helpers.ranking import ranks_of

BACKENDS = ["torch", pytest.param("faiss", marks=pytest.mark.skipif(
    not __import__("importlib").util.find_spec("faiss"), reason="faiss-cpu not installed"))]


def unit_pairs(n=60, d=16, noise=0.5, seed=0):
    g = torch.Generator().manual_seed(seed)
    reference = torch.nn.functional.normalize(torch.randn(n, d, generator=g), dim=1)
    query = torch.nn.functional.normalize(reference + noise * torch.randn(n, d, generator=g), dim=1)
    return query, reference


def row_scales(n, seed=1):
    """Per-row norms spread over two decades: enough to reorder a raw inner-product ranking."""
    return torch.from_numpy(np.random.default_rng(seed).uniform(0.1, 10.0, (n, 1)).astype(np.float32))


# ---- non-finite descriptors ------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("side", ["query", "reference"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_rows_raise_naming_the_side_and_the_count(backend, side, bad):
    query, reference = unit_pairs()
    broken = {"query": query.clone(), "reference": reference.clone()}
    broken[side][[3, 7, 11], 0] = bad
    # Before the check a NaN compared false everywhere, so its queries counted as hits.
    with pytest.raises(FloatingPointError, match=rf"3 of 60 {side} descriptors hold NaN/inf \(rows \[3, 7, 11\]"):
        recall_at_k(broken["query"], broken["reference"], backend=backend)


def test_non_finite_rows_raise_in_the_scorer_too():
    query, reference = unit_pairs()
    query[0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match="1 of 60 query"):
        ranks_of(query, reference)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gallery_index_refuses_non_finite_rows(backend):
    query, reference = unit_pairs()
    bad = reference.clone()
    bad[5] = float("nan")
    with pytest.raises(FloatingPointError, match="1 of 60 reference descriptors"):
        GalleryIndex(16, backend=backend).add(bad)
    index = GalleryIndex(16, backend=backend).add(reference)
    query[2, 4] = float("inf")
    with pytest.raises(FloatingPointError, match="1 of 60 query descriptors"):
        index.search(query, 5)


# ---- raw (unnormalised) descriptors: cosine on every backend ---------------------------------------------------
@pytest.mark.parametrize("backend", BACKENDS)
def test_raw_descriptors_rank_by_cosine(backend):
    query, reference = unit_pairs()
    expected = recall_at_k(query, reference, backend=backend)
    assert 0.1 < expected["R@1"] < 0.9  # neither trivial nor hopeless, so a wrong ranking shows
    raw_reference = reference * row_scales(60)
    # What raw inner products would have given: long references win whatever their direction.
    raw_ranks = ((query @ raw_reference.T) > (query * raw_reference).sum(1, keepdim=True)).sum(1)
    assert abs(float((raw_ranks == 0).float().mean()) - expected["R@1"]) > 0.1
    assert recall_at_k(3 * query, 3 * reference, backend=backend) == expected
    assert recall_at_k(query * row_scales(60, seed=2), raw_reference, backend=backend) == expected


@pytest.mark.parametrize("backend", BACKENDS)
def test_gallery_ranks_raw_descriptors_by_cosine(backend):
    query, reference = unit_pairs()
    scaled = GalleryIndex(16, backend=backend).add(reference * row_scales(60))
    exact = GalleryIndex(16, backend=backend).add(reference)
    split = pairs_split(60)
    exact_metrics = index_metrics(exact, query, split)
    assert index_metrics(scaled, query * 7, split) == exact_metrics == recall_at_k(query, reference)
    _, rows_scaled = scaled.search(query * 7, 5)
    _, rows_exact = exact.search(query, 5)
    assert torch.equal(rows_scaled, rows_exact)


def test_unit_rows_are_used_exactly_as_given():
    query, _ = unit_pairs()
    assert unit_rows(query, "query") is query  # no copy, no rounding: normalised inputs keep their numbers
    nearly = query * (1 + UNIT_TOLERANCE / 2)
    assert unit_rows(nearly, "query") is nearly
    off = query.clone()
    off[4] *= 2
    fixed = unit_rows(off, "query")
    assert torch.equal(fixed[:4], query[:4]) and torch.equal(fixed[5:], query[5:])
    torch.testing.assert_close(fixed[4], query[4])


def test_all_zero_rows_raise():
    query, reference = unit_pairs()
    reference[[1, 2]] = 0
    with pytest.raises(ValueError, match=r"2 of 60 reference descriptors are all zeros \(rows \[1, 2\]"):
        recall_at_k(query, reference)


# ---- the saved-gallery path of evaluate.py ---------------------------------------------------------------------
def gallery_eval(monkeypatch, tmp_path, query, reference, **cfg):
    """The saved-gallery path on the given descriptors (no network needed)."""
    return gallery_evaluate(monkeypatch, pairs_split(len(query), tmp_path), query, reference, **cfg)


def test_gallery_path_refuses_nan_before_saving_and_at_load(monkeypatch, tmp_path):
    query, reference = unit_pairs()
    nan_reference = reference.clone()
    nan_reference[9] = float("nan")
    with pytest.raises(FloatingPointError, match="1 of 60 reference descriptors hold NaN"):
        gallery_eval(monkeypatch, tmp_path, query, nan_reference, save=str(tmp_path / "g"))
    assert not (tmp_path / "g").exists()  # nothing half-made was saved
    healthy = gallery_eval(monkeypatch, tmp_path, query, reference, save=str(tmp_path / "g"))
    assert healthy["R@1"] == recall_at_k(query, reference)["R@1"]
    nan_query = query.clone()
    nan_query[:, 0] = float("nan")  # a diverged checkpoint's queries against a good saved gallery
    with pytest.raises(FloatingPointError, match="60 of 60 query descriptors hold NaN"):
        gallery_eval(monkeypatch, tmp_path, nan_query, None, load=str(tmp_path / "g"))


@pytest.mark.parametrize("constant", [1.0, 0.0])  # collapsed onto one point, or onto zero
def test_gallery_path_reports_a_collapse_as_zero(monkeypatch, tmp_path, constant):
    same = torch.full((60, 16), constant)
    with pytest.warns(UserWarning, match="collapsed"):
        built = gallery_eval(monkeypatch, tmp_path, same.clone(), same, save=str(tmp_path / "g"))
    assert built["R@1"] == built["R@1%"] == 0.0 and built["reference_spread"] == 0.0  # ties would give 100%
    assert not (tmp_path / "g").exists()  # a collapsed gallery is not saved


def test_loading_a_gallery_uses_the_spread_measured_when_it_was_built(monkeypatch, tmp_path):
    query, reference = unit_pairs()
    gallery_eval(monkeypatch, tmp_path, query, reference, save=str(tmp_path / "g"))
    info = json.loads((tmp_path / "g" / "gallery.json").read_text())
    assert info["reference_spread"] == pytest.approx(float(reference.std(dim=0).sum()))
    (tmp_path / "g" / "gallery.json").write_text(json.dumps({**info, "reference_spread": 1e-6}))
    with pytest.warns(UserWarning, match="collapsed"):
        loaded = gallery_eval(monkeypatch, tmp_path, query, None, load=str(tmp_path / "g"))
    assert loaded["R@1"] == 0.0 and loaded["reference_spread"] == 1e-6


def test_gallery_path_refuses_a_gallery_saved_without_its_checks(monkeypatch, tmp_path):
    query, reference = unit_pairs()
    gallery_eval(monkeypatch, tmp_path, query, reference, save=str(tmp_path / "g"))
    info = json.loads((tmp_path / "g" / "gallery.json").read_text())
    del info["reference_spread"]
    (tmp_path / "g" / "gallery.json").write_text(json.dumps(info))
    with pytest.raises(ConfigError, match="lacks reference_spread.*older geoloc.*gallery.save="):
        gallery_eval(monkeypatch, tmp_path, query, None, load=str(tmp_path / "g"))


def test_validation_and_gallery_paths_give_the_same_metrics(monkeypatch, tmp_path):
    from conftest import tiny_task

    query, reference = unit_pairs()
    task = tiny_task(dim=16)
    validation = task.validation_epoch_end({"query": query, "reference": reference})
    gallery = gallery_eval(monkeypatch, tmp_path, query, reference)
    assert {k: gallery[k] for k in validation} == validation
