"""evaluate.py gallery.save / gallery.load: a saved GalleryIndex answers the queries with the exact recall."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from geoloc.config import ConfigError
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval import GalleryIndex, recall_at_k
from geoloc.eval.retrieval_metrics import index_metrics
from geoloc.launch import run

from conftest import TINY, compose_evaluate, compose_train
from helpers.gallery_runs import gallery_evaluate


@pytest.fixture
def trained(tiny_cvusa, tmp_path):
    run_dir = tmp_path / "run"
    run.train(compose_train([*TINY, f"dataset.root={tiny_cvusa}", f"run_dir={run_dir}", "trainer.max_epochs=1"]))
    return run_dir / "best.pt"


def evaluate(tmp_path, ckpt, *extra):
    return run.evaluate(compose_evaluate([f"ckpt={ckpt}", "progress=false", "device=cpu",
                                          f"run_dir={tmp_path / 'eval'}", *extra]))


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["torch", "faiss"])
def test_saved_flat_gallery_gives_the_exact_recall(trained, tmp_path, backend):
    if backend == "faiss":
        pytest.importorskip("faiss")
    exact = evaluate(tmp_path, trained)
    folder = tmp_path / f"gallery_{backend}"
    built = evaluate(tmp_path, trained, f"gallery.save={folder}", f"gallery.backend={backend}")
    info = json.loads((folder / "gallery.json").read_text())
    assert info["num_references"] == 8 and info["backend"] == backend and info["kind"] == "flat"
    out = tmp_path / "loaded.json"
    loaded = evaluate(tmp_path, trained, f"gallery.load={folder}", f"metrics_out={out}")
    for key in ("R@1", "R@5", "R@10", "R@1%"):
        assert built[key] == exact[key] and loaded[key] == exact[key], key
    assert json.loads(out.read_text())["num_queries"] == 8


def test_gallery_config_errors(trained, tmp_path):
    with pytest.raises(ConfigError, match="not both"):
        evaluate(tmp_path, trained, "gallery.save=a", "gallery.load=b")
    with pytest.raises(ConfigError, match="ivfpq"):
        evaluate(tmp_path, trained, "gallery.kind=ivfpq", "gallery.save=a")
    with pytest.raises(FileNotFoundError, match="gallery.save="):
        evaluate(tmp_path, trained, f"gallery.load={tmp_path / 'none'}")


def test_index_metrics_match_recall_at_k_and_ivfpq_stays_close():
    g = torch.Generator().manual_seed(0)
    reference = torch.nn.functional.normalize(torch.randn(2000, 32, generator=g), dim=1)
    query = torch.nn.functional.normalize(reference + 0.15 * torch.randn(2000, 32, generator=g), dim=1)
    exact = recall_at_k(query, reference)
    assert 0.2 < exact["R@1"] < 1.0  # neither trivial nor hopeless
    split = RetrievalSplit("pairs", "/data", [f"q{i}" for i in range(2000)], [f"r{i}" for i in range(2000)],
                           np.arange(2000))
    for backend in ("torch", "faiss"):
        if backend == "faiss":
            pytest.importorskip("faiss")
        index = GalleryIndex(32, backend=backend).add(reference)
        assert index_metrics(index, query, split) == exact
    ivfpq = GalleryIndex(32, backend="faiss", kind="ivfpq", nlist=16, m=8, nbits=6, nprobe=16).add(reference)
    approx = index_metrics(ivfpq, query, split)
    assert approx["R@1%"] > 0.8 * exact["R@1%"]


@pytest.mark.parametrize("backend", ["torch", "faiss"])
def test_a_saved_gallery_scores_every_image_of_the_building(monkeypatch, tmp_path, backend):
    """University-1652 satellite -> drone: each satellite query's relevant references are all the drone images of
    its building. The saved gallery scores them as the exact path does (R@K and AP); ranking against the one
    "positive" drone image instead would miss every query whose first image is not on top."""
    if backend == "faiss":
        pytest.importorskip("faiss")
    from geoloc.eval.retrieval_metrics import split_metrics

    g = torch.Generator().manual_seed(0)
    buildings, views = 4, 5
    query = torch.nn.functional.normalize(torch.randn(buildings, 16, generator=g), dim=1)
    reference = torch.nn.functional.normalize(query.repeat_interleave(views, 0)
                                              + 0.3 * torch.randn(buildings * views, 16, generator=g), dim=1)
    labels = np.arange(buildings).repeat(views)
    split = RetrievalSplit("u1652/satellite_to_drone", tmp_path, [f"s{i}.jpg" for i in range(buildings)],
                           [f"d{j}.jpg" for j in range(buildings * views)], np.arange(buildings) * views,
                           query_labels=np.arange(buildings), reference_labels=labels, query_view="aerial")
    exact = split_metrics(query, reference, split)
    positive_only = recall_at_k(query, reference, positives=split.positives)
    assert exact["R@1"] == 1.0 and positive_only["R@1"] < 0.5  # the building is on top, its first image is not
    for cfg in (dict(save=str(tmp_path / "g"), backend=backend), dict(load=str(tmp_path / "g"))):
        got = gallery_evaluate(monkeypatch, split, query, reference, **cfg)
        assert {k: got[k] for k in exact} == exact
