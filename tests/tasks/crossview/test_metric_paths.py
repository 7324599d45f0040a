"""Every path that reports a number about a split gives the same numbers (docs/conventions.md "Relevance": it is
a property of the split, defined once): training's validation, evaluate.py (exact), evaluate.py with a saved
gallery (torch and FAISS flat, saved then loaded; an approximate FAISS kind for everything but AP),
`recall_at_k(backend="faiss")`, the recall-curve data of the figures, and localize's top-k. On a one-to-one split,
a VIGOR-like split, and a University-1652-like split in both directions (satellite -> drone has several relevant
drone images per query).

The networks are a two-convolution backbone registered here (a tiny VGG's descriptors of these tiny images are all
but collapsed) and a global-pooling head, trained one epoch: seconds, and descriptors with a healthy spread.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from geoloc.apps.localize import Localizer, read_street
from geoloc.engine import checkpoint as ckpt_io
from geoloc.eval import recall_at_k
from geoloc.eval.scoring import rank, top_k
from geoloc.launch import run
from geoloc.registry import register
from geoloc.synthetic import generate
from geoloc.tasks.crossview import figures
from geoloc.tasks.crossview import validation as validation_module
from geoloc.tasks.crossview.crossview_config import evaluated_dataset
from geoloc.tasks.crossview.data_config import parse_dataset
from geoloc.tasks.crossview.datasets import build_eval
from geoloc.tasks.crossview.crossview_run import restored_task, stored_config
from omegaconf import OmegaConf
from plugins.tiny_cnn import TinyCNN

from conftest import TINY, compose_evaluate, compose_train, write_cvusa

pytest.importorskip("faiss")
pytestmark = pytest.mark.slow  # three one-epoch trainings and about thirty evaluations: about 45 s on 2 cores


@register("backbone", "metric_paths_convs")
def metric_paths_convs(width: int = 8, pretrained: bool = False, weights_path=None, batchnorm: bool = False):
    return TinyCNN(int(width))  # two strided convolutions: descriptors differ from image to image at any weights


NET = [t for t in TINY if not t.startswith(("dataset=", "backbone.", "head"))] + [
    "backbone.name=metric_paths_convs", "backbone.width=8", "head=gap"]
VIGOR = ["dataset=vigor", "dataset.cities=[Chicago,NewYork]", "dataset.check_files=exists"]
U1652 = ["dataset=u1652", "dataset.check_files=exists"]
CASES = {  # case: (run, dataset overrides of its evaluation)
    "one_to_one": ("pairs", []),
    "vigor": ("vigor", VIGOR),
    "u1652_drone_to_satellite": ("u1652", [*U1652, "dataset.direction=drone_to_satellite"]),
    "u1652_satellite_to_drone": ("u1652", [*U1652, "dataset.direction=satellite_to_drone"]),
}
LOCALIZED = ("one_to_one", "vigor")  # localize answers street panoramas only


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """{run: (dataset root, checkpoint, validation metrics of training)} of three one-epoch runs."""
    base = tmp_path_factory.mktemp("paths")
    roots = {
        "pairs": write_cvusa(base / "cvusa", n_train=12, n_val=10),
        "vigor": generate("vigor", base / "vigor", seed=3, preset="vigor_tiny", progress=False, val=5),
        "u1652": generate("u1652", base / "u1652", seed=1, preset="u1652_tiny", progress=False, val=5,
                          drone_views=5, extra_gallery=2),
    }
    extra = {"pairs": ["dataset=cvusa"], "vigor": VIGOR, "u1652": [*U1652, "sampler=no_duplicate",
                                                                   "dataset.batch_size=3"]}
    out = {}
    for name, root in roots.items():
        run_dir = base / f"run_{name}"
        best = run.train(compose_train([*NET, *extra[name], f"dataset.root={root}", f"run_dir={run_dir}",
                                        "trainer.max_epochs=1"]))
        out[name] = root, run_dir / "best.pt", best
    return out


def evaluate(tmp_path, ckpt, root, dataset, *extra) -> dict:
    run_dir = tmp_path / f"eval{len(list(tmp_path.glob('eval*')))}"
    return run.evaluate(compose_evaluate([f"ckpt={ckpt}", "progress=false", "device=cpu", f"run_dir={run_dir}",
                                          f"dataset.root={root}", *dataset, *extra]))


def exact_descriptors(tmp_path, ckpt, root, dataset, monkeypatch) -> tuple[dict, torch.Tensor, torch.Tensor, object]:
    """(evaluate.py's metrics, the query and reference descriptors validation scored, the split)."""
    seen = {}
    real = validation_module.split_metrics

    def spy(query, reference, split, *args, **kwargs):
        seen.update(query=query, reference=reference, split=split)
        return real(query, reference, split, *args, **kwargs)

    monkeypatch.setattr(validation_module, "split_metrics", spy)
    metrics = evaluate(tmp_path, ckpt, root, dataset)
    monkeypatch.undo()
    return metrics, seen["query"], seen["reference"], seen["split"]


def figures_curve(ckpt, root, dataset, tmp_path, monkeypatch) -> dict:
    """The recall curve crossview_figures plots for this split, as it computes it."""
    state = ckpt_io.load(ckpt)
    stored = stored_config(state)
    task = restored_task(state, ckpt, stored)
    requested = OmegaConf.from_dotlist([o for o in [*dataset, f"dataset.root={root}"] if not o.startswith("dataset=")])
    name = next((o.split("=")[1] for o in dataset if o.startswith("dataset=")), None)
    section = OmegaConf.to_container(requested.get("dataset", {}))
    section = evaluated_dataset(stored.dataset, {**({"name": name} if name else {}), **section})
    data_cfg, reader = parse_dataset(section)
    data = build_eval(data_cfg, reader, data_cfg.split)
    task.validate_on(data.split)
    curves = []
    real = figures.recall_curve
    monkeypatch.setattr(figures, "recall_curve", lambda *a, **k: curves.append(real(*a, **k)) or curves[-1])
    figures.crossview_figures(task, data, tmp_path / "figures", torch.device("cpu"), batch_size=4)
    monkeypatch.undo()
    return curves[0]


def assert_same_top_k(got_rows, got_scores, all_scores: np.ndarray, k: int, tol: float = 1e-5):
    """got (localize's top-k, encoded alone) against the exact scores of every reference: the same scores within
    tol, and the same rows except where exact scores tie within tol."""
    order = sorted(range(len(all_scores)), key=lambda j: (-all_scores[j], j))[:k]
    np.testing.assert_allclose(got_scores, all_scores[order], atol=tol)
    for row, want in zip(got_rows, order):
        if row != want:
            assert abs(all_scores[row] - all_scores[want]) <= tol, (row, want)
    boundary = all_scores[order[-1]]
    firm = {j for j in order if all_scores[j] > boundary + tol}
    assert firm <= set(got_rows)


@pytest.mark.parametrize("case", list(CASES))
def test_every_path_gives_the_same_numbers(runs, case, tmp_path, monkeypatch):
    name, dataset = CASES[case]
    root, ckpt, validation = runs[name]
    exact, query, reference, split = exact_descriptors(tmp_path, ckpt, root, dataset, monkeypatch)
    keys = [k for k in exact if k not in ("num_queries", "num_references", "reference_spread")]
    assert exact["reference_spread"] > 0.05  # healthy descriptors: nothing here is decided by a collapse
    if case != "u1652_satellite_to_drone":  # training validates drone -> satellite (its pairs)
        assert {k: validation[k] for k in keys} == {k: exact[k] for k in keys}

    for backend in ("torch", "faiss"):
        folder = tmp_path / f"gallery_{backend}"
        built = evaluate(tmp_path, ckpt, root, dataset, f"gallery.save={folder}", f"gallery.backend={backend}")
        loaded = evaluate(tmp_path, ckpt, root, dataset, f"gallery.load={folder}")
        assert json.loads((folder / "gallery.json").read_text())["kind"] == "flat"
        assert built == exact and loaded == exact, backend

    approximate = evaluate(tmp_path, ckpt, root, dataset, f"gallery.save={tmp_path / 'hnsw'}",
                           "gallery.backend=faiss", "gallery.kind=hnsw")
    assert {k: approximate[k] for k in keys if k != "AP"} == {k: exact[k] for k in keys if k != "AP"}
    assert "AP" not in approximate  # a top-k list does not rank the whole gallery

    if split.query_labels is None:  # the recall_at_k contract: the FAISS backend gives the torch numbers
        positives = None if split.one_to_one else split.positives
        for backend in ("torch", "faiss"):
            got = recall_at_k(query, reference, positives=positives, semi_positives=split.semi_positives,
                              backend=backend)
            assert got == {k: exact[k] for k in got}, backend

    curve = figures_curve(ckpt, root, dataset, tmp_path, monkeypatch)
    assert {k: curve[k] for k in keys if k in curve} == {k: exact[k] for k in keys if k in curve}
    assert {"R@1", "R@5", "R@1%"} <= set(curve)

    if case in LOCALIZED:
        localizer = Localizer.load(ckpt, tmp_path / "gallery_torch", device="cpu")
        scores = (query @ reference.T).numpy()
        ranks = rank(query, reference, split.relevance).ranks
        for i, path in enumerate(split.queries):
            answer = localizer.localize(read_street(path), topk=5, heading=0, path=path).to_json()
            got_rows = [t["row"] for t in answer["topk"]]
            assert_same_top_k(got_rows, [t["score"] for t in answer["topk"]], scores[i], 5)
            assert answer["truth"]["row"] == split.positives[i]
            if ranks[i] < 5 and np.sort(np.abs(scores[i] - scores[i, split.positives[i]]))[1] > 1e-5:
                assert answer["truth"]["rank"] == ranks[i] + 1
        assert torch.equal(top_k(query, reference, 5)[1], torch.tensor(
            [sorted(range(len(s)), key=lambda j: (-s[j], j))[:5] for s in scores.tolist()]))


def test_the_u1652_data_tell_the_relevance_rules_apart(runs, tmp_path, monkeypatch):
    """Satellite -> drone: several relevant drone images per query, so the building rule and the old "one positive
    image" rule differ here; a gallery ranking against the positive alone would fail the test above."""
    root, ckpt, _ = runs["u1652"]
    exact, query, reference, split = exact_descriptors(tmp_path, ckpt, root, CASES["u1652_satellite_to_drone"][1],
                                                       monkeypatch)
    relevant = split.relevance.relevant
    assert (relevant >= 0).sum(dim=1).min() == 5  # every drone view of the building
    one_image = recall_at_k(query, reference, positives=split.positives)
    assert any(one_image[k] != exact[k] for k in ("R@1", "R@5", "R@10"))
