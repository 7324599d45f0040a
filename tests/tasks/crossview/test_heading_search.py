"""Unknown heading (dataset.random_heading) and limited field of view (dataset.fov): the Q×K×N search against a
loop, exact recovery with a shift-covariant encoder, the train-time window, evaluate.py's overrides, errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from geoloc.config import ConfigError
from geoloc.data.io import read_rgb
from geoloc.data.polar import aerial_to_polar
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.launch import run
from geoloc.registry import register
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.data.relevance import Relevance
from geoloc.eval import scoring
from geoloc.tasks.crossview.datasets import ViewImages
from geoloc.tasks.crossview.heading import heading_metrics
from geoloc.tasks.crossview.transforms import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    align_query,
    image_tensor,
)
from geoloc.tasks.crossview.views import circular_error_deg, eval_heading, north_window
from torch import nn

from conftest import TINY, compose_evaluate, compose_train, tiny_task, write_cvusa
from helpers.crossview_runs import pairs_of, eval_data_of


def unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True)


def loop_search(query, reference, positives):
    """score(i, j) = max_k <q_ik, r_j>, one pair at a time."""
    ranks, best = [], []
    for i in range(query.shape[0]):
        scores = [max(float(query[i, k] @ reference[j]) for k in range(query.shape[1]))
                  for j in range(reference.shape[0])]
        p = int(positives[i])
        ranks.append(sum(s > scores[p] for j, s in enumerate(scores) if j != p))
        best.append(max(range(query.shape[1]), key=lambda k: float(query[i, k] @ reference[p])))
    return ranks, best


@pytest.mark.parametrize("chunk,budget", [(None, 2 ** 25), (1, 6), (3, 36)])  # (1, 6): one reference per block
def test_search_matches_a_loop_over_pairs_and_headings(monkeypatch, chunk, budget):
    monkeypatch.setattr(scoring, "SCORE_BUDGET", budget)
    g = torch.Generator().manual_seed(0)
    query, reference = unit(torch.randn(7, 6, 4, generator=g)), unit(torch.randn(9, 4, generator=g))
    positives = torch.randint(0, 9, (7,), generator=g)
    relevance = Relevance.from_positives(positives, 9)
    found = scoring.rank(query, reference, relevance, chunk_size=chunk)
    ranks, best = found.ranks, found.best_candidate
    expected_ranks, expected_best = loop_search(query, reference, positives)
    assert ranks.tolist() == expected_ranks and best.tolist() == expected_best
    truth = torch.rand(7, generator=g) * 360
    metrics = heading_metrics(query, reference, truth, relevance=relevance)
    error = circular_error_deg(np.array(expected_best) * 60.0, truth.double().numpy())
    assert metrics["R@1"] == pytest.approx(np.mean(np.array(expected_ranks) < 1))
    assert metrics["R@5"] == pytest.approx(np.mean(np.array(expected_ranks) < 5))
    assert metrics["heading_median_deg"] == pytest.approx(np.median(error))
    assert metrics["heading_mean_deg"] == pytest.approx(error.mean())
    assert metrics["heading_within_20deg"] == pytest.approx(np.mean(error <= 20))


class PixelEncoder(nn.Module):
    """The input's pixels around mid-grey as its descriptor, 0 where the canvas is empty (black): pointwise, so
    exactly shift-covariant, and a heading search with it is a brute circular correlation of the aligned images."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        raw = x * torch.tensor(IMAGENET_STD)[:, None, None] + torch.tensor(IMAGENET_MEAN)[:, None, None]
        return unit(((raw - 0.5) * (raw > 1e-3)).flatten(1))


def write_polar_pairs(root, n: int, hw=(16, 64)):
    """A CVUSA layout whose panoramas are exactly the polar transform of their aerial images (lossless PNG bytes
    under the .jpg names: files are decoded by content), so polar alignment makes query and reference equal."""
    write_cvusa(root, n_train=2, n_val=n, aerial=64, pano=hw)
    rng = np.random.default_rng(5)
    for i in range(3, n + 3):
        aerial = rng.integers(1, 256, (64, 64, 3), dtype=np.uint8)  # never black: black is the empty canvas
        (root / f"bingmap/19/{i:07d}.jpg").write_bytes(cv2.imencode(".png", aerial)[1].tobytes())
        pano = aerial_to_polar(aerial, hw)
        (root / f"streetview/panos/{i:07d}.jpg").write_bytes(cv2.imencode(".png", pano)[1].tobytes())
    return root


@pytest.mark.parametrize("fov", [360, 90])
def test_a_shift_covariant_encoder_finds_the_heading_to_the_column(tmp_path, fov):
    root = write_polar_pairs(tmp_path / "cvusa", n=6)
    cfg = CrossViewDataConfig(name="cvusa", root=str(root), alignment="polar", aerial_size=64, pano_size=[16, 64],
                              fov=fov, random_heading=True, heading_steps=64)  # one candidate per column
    data = eval_data_of(cfg, "val")
    task = tiny_task()
    task.model.query, task.model.reference = PixelEncoder(), PixelEncoder()
    task.validate_on(data.split, heading_search=True)
    batch = torch.utils.data.default_collate([data.pairs[i] for i in range(6)])
    assert batch["query"].shape == (6, 64, 3, 16, 64)
    metrics = task.validation_epoch_end(task.validation_step(batch))
    assert metrics["R@1"] == 1.0
    # the view was cut at the whole column nearest the true heading; the search must land on exactly that column
    truth = np.array([eval_heading(i) for i in range(6)])
    cut = np.round(truth * 64 / 360) * 360 / 64
    assert metrics["heading_mean_deg"] == pytest.approx(circular_error_deg(cut, truth).mean())
    assert metrics["heading_mean_deg"] <= 360 / 64 / 2


def tiny_cfg(root, **kw):
    return CrossViewDataConfig(**{**dict(name="cvusa", root=str(root), aerial_size=32, pano_size=[16, 64],
                                         joint_flip_rotate=False, color_jitter=0.0), **kw})


def test_training_sees_the_window_at_north_or_at_a_random_bearing(tiny_cvusa):
    pano = read_rgb(tiny_cvusa / "streetview/panos/0000004.jpg")
    north = image_tensor(align_query(north_window(pano, 90, 0.0), tiny_cfg(tiny_cvusa)))
    known = pairs_of(tiny_cfg(tiny_cvusa, fov=90), "train", train=True)
    assert torch.equal(known[(3, 0)]["query"], north)
    assert torch.equal(pairs_of(tiny_cfg(tiny_cvusa, fov=90), "train", train=False)[3]["query"], north)
    queries = ViewImages([tiny_cvusa / "streetview/panos/0000004.jpg"], "panorama",
                                   tiny_cfg(tiny_cvusa, fov=90))
    assert torch.equal(queries[0]["image"], north)  # galleries apart from the queries (VIGOR) see them at north too
    random = pairs_of(tiny_cfg(tiny_cvusa, fov=90, random_heading=True), "train", train=True)
    heading = float(np.random.default_rng((0, 0, 3)).uniform(0, 360))  # the item's augmentation RNG, first draw
    assert torch.equal(random[(3, 0)]["query"], image_tensor(align_query(north_window(pano, 90, heading),
                                                                          tiny_cfg(tiny_cvusa))))
    assert not torch.equal(random[(3, 0)]["query"], random[(3, 1)]["query"])


def test_a_full_view_trains_exactly_as_before_with_or_without_random_heading(tiny_cvusa):
    """fov 360 shows the whole north-aligned canvas: no RNG draw, so the default run's numerics stay identical."""
    kw = dict(rotation_deg=20, color_jitter=0.3, joint_flip_rotate=True)
    plain = pairs_of(tiny_cfg(tiny_cvusa, **kw), "train", train=True)
    heading = pairs_of(tiny_cfg(tiny_cvusa, random_heading=True, **kw), "train", train=True)
    for key in [(0, 0), (5, 3)]:
        assert torch.equal(plain[key]["query"], heading[key]["query"])
        assert torch.equal(plain[key]["reference"], heading[key]["reference"])


@pytest.mark.slow
def test_evaluate_sets_the_test_condition_over_the_trained_one(tmp_path):
    root = write_cvusa(tmp_path / "cvusa", n_train=8, n_val=6)
    run_dir = tmp_path / "run"
    run.train(compose_train([*TINY, f"dataset.root={root}", f"run_dir={run_dir}", "trainer.max_epochs=1",
                             "dataset.fov=90", "dataset.random_heading=true", "dataset.heading_steps=4",
                             "figures=true"]))
    assert (run_dir / "top5.png").is_file()  # the figures show each query at its known heading
    ckpt = f"ckpt={run_dir / 'last.pt'}"
    common = [ckpt, "progress=false", f"run_dir={tmp_path / 'e'}"]
    searched = run.evaluate(compose_evaluate([*common, "dataset.heading_steps=6"]))  # fov 90 and random: stored
    assert 0 <= searched["heading_median_deg"] <= 180 and "heading_within_10deg" in searched
    known = run.evaluate(compose_evaluate([*common, "dataset.random_heading=false", "dataset.fov=360"]))
    assert "heading_median_deg" not in known and known["num_queries"] == 6
    with pytest.raises(ConfigError, match="dataset.random_heading=true"):
        run.evaluate(compose_evaluate([*common, "gallery.save=" + str(tmp_path / "g")]))


@register("dataset", "heading_test_split")
def heading_test_split(root: str, split: str, view: str = "panorama") -> RetrievalSplit:
    """Four tiny CVUSA panoramas against two aerial tiles (two queries per place): not one-to-one."""
    root = Path(root)
    return RetrievalSplit(name="heading_test", root=root, query_view=view,
                          queries=[root / f"streetview/panos/{i:07d}.jpg" for i in range(1, 5)],
                          references=[root / f"bingmap/19/{i:07d}.jpg" for i in range(1, 3)],
                          positives=np.array([0, 0, 1, 1]))


@pytest.mark.parametrize("overrides,match", [
    ({"fov": 0}, r"dataset.fov must lie in \(0, 360\]"),
    ({"fov": 400}, r"dataset.fov must lie in \(0, 360\]"),
    ({"heading_steps": 0}, "dataset.heading_steps must be >= 1"),
    ({"fov": 90, "view": "image", "alignment": "none"}, "photo queries"),
])
def test_bad_heading_settings_say_what_to_do(tiny_cvusa, overrides, match):
    section = {"name": "heading_test_split", "root": str(tiny_cvusa), "aerial_size": 32, "pano_size": [16, 64],
               **overrides}
    with pytest.raises(ConfigError, match=match):
        eval_data_of(section, "val")


def test_bad_heading_settings_fail_at_start(tmp_path):
    cfg = compose_train([*TINY, f"dataset.root={tmp_path / 'absent'}", f"run_dir={tmp_path / 'run'}",
                         "dataset.fov=0"])
    with pytest.raises(ConfigError, match=r"dataset.fov must lie in \(0, 360\]"):
        run.train(cfg)
    assert not (tmp_path / "run").exists()


def test_a_checkpoint_from_before_the_heading_keys_still_resumes_at_their_old_values(tiny_cvusa, tmp_path):
    """A config stored before dataset.fov / random_heading / heading_steps existed compares, in the task's canonical
    form, equal to today's request at their defaults, and different from a narrower view."""
    from omegaconf import OmegaConf

    from geoloc.launch import resume
    from geoloc.tasks.crossview import RESUME_MAY_CHANGE, canonical_config

    requested = compose_train([*TINY, f"dataset.root={tiny_cvusa}", f"run_dir={tmp_path}"])
    stored = OmegaConf.to_container(requested, resolve=True)
    for key in ("fov", "random_heading", "heading_steps"):
        del stored["dataset"][key]
    stored = OmegaConf.create(stored)
    allowed = resume.RESUME_MAY_CHANGE + RESUME_MAY_CHANGE
    assert resume.config_differences(canonical_config(stored), canonical_config(requested), allowed) == []
    narrower = compose_train([*TINY, f"dataset.root={tiny_cvusa}", f"run_dir={tmp_path}", "dataset.fov=90"])
    assert resume.config_differences(canonical_config(stored), canonical_config(narrower), allowed) == [
        "dataset.fov: 360.0 → 90.0"]


def test_the_heading_search_scores_queries_apart_as_it_scores_pairs(tiny_cvusa, tmp_path, one_thread, monkeypatch):
    """A split that is not one-to-one (its queries and gallery read apart: VIGOR, your own data, a padded gallery)
    searches the same candidate headings: on a one-to-one split read both ways, the metrics are the same."""
    from geoloc.engine import Trainer, TrainerConfig
    from geoloc.tasks.crossview.datasets import EvalData, eval_sets
    from helpers.crossview_runs import split_of

    cfg = tiny_cfg(tiny_cvusa, fov=90, random_heading=True, heading_steps=4)
    split = split_of(cfg, "val")
    pairs = eval_sets(cfg, split)
    apart = EvalData(split, queries=ViewImages(split.queries, "panorama", cfg, heading_search=True),
                     references=ViewImages(split.references, "aerial", cfg))
    item = apart.queries[2]
    assert item["image"].shape[0] == 4 and item["heading"] == eval_heading(2)
    assert torch.equal(item["image"], pairs.pairs[2]["query"])
    from geoloc.eval import keys

    monkeypatch.setattr(keys, "COLLAPSE_SPREAD", 0.0)  # an untrained tiny network: score it anyway
    task = tiny_task()
    task.validate_on(split, heading_search=True)
    trainer = Trainer(TrainerConfig(device="cpu", num_workers=0, progress=False), run_dir=tmp_path)
    by_pairs, by_sides = (trainer.validate(task, task.val_dataloaders(data, 3, trainer.engine))
                          for data in (pairs, apart))
    assert "heading_median_deg" in by_sides and by_sides == pytest.approx(by_pairs)
    assert by_sides["heading_median_deg"] < 180 and by_sides["R@5"] > 0  # scored, not reported at its worst


def test_a_split_that_is_not_one_to_one_evaluates_with_an_unknown_heading(tiny_cvusa):
    section = {"name": "heading_test_split", "root": str(tiny_cvusa), "aerial_size": 32, "pano_size": [16, 64],
               "fov": 180, "random_heading": True, "heading_steps": 3}
    data = eval_data_of(section, "val")
    assert data.pairs is None and data.queries[1]["image"].shape == (3, 3, 32, 32)
    assert data.queries[1]["heading"] == eval_heading(1) and data.references[1]["image"].shape == (3, 32, 32)
