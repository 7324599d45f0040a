"""A tiny CPU train → kill → resume → evaluate run, end to end, in seconds."""

from __future__ import annotations

import json

import pytest
import torch
from geoloc.engine import checkpoint as ckpt_io
from geoloc.launch import run
from geoloc.tasks.crossview.transforms import normalise

from omegaconf import OmegaConf

from conftest import REALDATA, compose_evaluate
from helpers.crossview_runs import pairs_of, task_of, train_cfg, train_until_killed, val_records


@pytest.mark.slow
def test_kill_and_resume_reproduce_the_uninterrupted_run(tiny_cvusa, tmp_path, monkeypatch):
    full = tmp_path / "full"
    run.train(train_cfg(tiny_cvusa, full, "trainer.max_epochs=3"))

    # the same run, killed in the middle of its second epoch (3 steps per epoch)
    killed = tmp_path / "killed"
    train_until_killed(train_cfg(tiny_cvusa, killed, "trainer.max_epochs=3"), monkeypatch, global_step=4)
    assert ckpt_io.load(killed / "last.pt")["epoch"] == 0  # the last good checkpoint survived the kill

    resumed = tmp_path / "resumed"
    run.train(train_cfg(tiny_cvusa, resumed, "trainer.max_epochs=3", f"ckpt={killed / 'last.pt'}"))

    a, b = ckpt_io.load(full / "last.pt"), ckpt_io.load(resumed / "last.pt")
    assert a["epoch"] == b["epoch"] == 2
    for key, tensor in a["task"].items():
        assert torch.equal(tensor, b["task"][key]), key  # bit-exact on CPU, GMS queue buffers included
    full_val, resumed_val = val_records(full), val_records(resumed)
    assert full_val[-1]["val/R@1"] == resumed_val[-1]["val/R@1"]
    assert full_val[-1]["val/R@1%"] == resumed_val[-1]["val/R@1%"]

    # evaluate.py reproduces the best epoch's validation numbers from best.pt
    out = tmp_path / "metrics.json"
    metrics = run.evaluate(compose_evaluate([f"ckpt={full / 'best.pt'}", f"metrics_out={out}", "progress=false",
                                             f"run_dir={tmp_path / 'eval'}"]))
    saved = json.loads(out.read_text())
    assert saved["num_queries"] == 8 and set(saved) >= {"R@1", "R@5", "R@10", "R@1%"}
    best = ckpt_io.load(full / "best.pt")
    best_epoch_val = [r for r in full_val if r["val/R@1"] == best["best_metric"]][0]
    for key in ("R@1", "R@5", "R@10", "R@1%"):
        assert metrics[key] == pytest.approx(best_epoch_val[f"val/{key}"], abs=1e-9)


@pytest.mark.slow
def test_evaluate_refuses_a_checkpoint_that_does_not_match_its_config(tiny_cvusa, tmp_path):
    run_dir = tmp_path / "run"
    run.train(train_cfg(tiny_cvusa, run_dir, "trainer.max_epochs=1"))
    state = ckpt_io.load(run_dir / "best.pt")
    state["config"] = state["config"].replace("dim: 16", "dim: 32")
    bad = tmp_path / "bad.pt"
    ckpt_io.save_atomic(state, bad)
    with pytest.raises(ValueError, match="does not match the model built from its config"):
        run.evaluate(compose_evaluate([f"ckpt={bad}", "progress=false", f"run_dir={tmp_path / 'e'}"]))


def test_figures_are_written_after_training(tiny_cvusa, tmp_path):
    run_dir = tmp_path / "run"
    run.train(train_cfg(tiny_cvusa, run_dir, "trainer.max_epochs=1", "figures=true"))
    for name in ("attention.png", "top5.png", "recall_curve.png"):
        assert (run_dir / name).stat().st_size > 1000, name
    assert any((run_dir / "tb").rglob("projector_config.pbtxt"))  # descriptors for the embedding projector


@pytest.mark.slow
@pytest.mark.skipif(not (REALDATA / "cvusa_mini").is_dir(), reason="../shared/realdata not present")
def test_a_checkpoint_evaluates_on_the_real_cvusa_samples(tiny_cvusa, tmp_path):
    run_dir = tmp_path / "run"
    run.train(train_cfg(tiny_cvusa, run_dir, "trainer.max_epochs=1"))
    out = tmp_path / "real.json"
    metrics = run.evaluate(compose_evaluate([
        f"ckpt={run_dir / 'best.pt'}", "dataset=cvusa", f"dataset.root={REALDATA / 'cvusa_mini'}",
        "dataset.split=val", f"metrics_out={out}", "progress=false", f"run_dir={tmp_path / 'e'}"]))
    rows = (REALDATA / "cvusa_mini/splits/val-19zl.csv").read_text().split()
    assert json.loads(out.read_text())["num_queries"] == metrics["num_queries"] == len(rows)
    # Five references put every match in the top 5, so R@5 says nothing here; R@1 is checked against descriptors
    # computed from the checkpoint and the real images outside evaluate(), ranked in float64.
    state = ckpt_io.load(run_dir / "best.pt")
    stored = OmegaConf.create(state["config"])
    task = task_of(stored)
    task.load_state_dict(state["task"])
    real = OmegaConf.merge(stored.dataset, {"root": str(REALDATA / "cvusa_mini")})
    pairs = pairs_of(real, "val", train=False)
    with torch.no_grad():
        query, reference = task.eval().model(normalise(torch.stack([pairs[i]["query"] for i in range(len(pairs))])),
                                             normalise(torch.stack([pairs[i]["reference"] for i in range(len(pairs))])))
    sim = query.double() @ reference.double().t()
    ranks = (sim > sim.diagonal()[:, None]).sum(1)
    assert metrics["R@1"] == pytest.approx(float((ranks == 0).double().mean()), abs=1e-9)
    assert metrics["R@1%"] == metrics["R@1"]  # K = max(1, floor(5 / 100)) = 1


def test_a_collapsed_network_scores_zero_not_one_hundred():
    from conftest import tiny_task

    task = tiny_task(dim=8, batchnorm=False)
    same = torch.nn.functional.normalize(torch.ones(6, 8), dim=1)
    with pytest.warns(UserWarning, match="collapsed"):
        metrics = task.validation_epoch_end({"query": same, "reference": same.clone()})
    assert metrics["R@1"] == 0.0  # ties alone would have given 100%
    with pytest.raises(FloatingPointError, match="NaN"):
        task.validation_epoch_end({"query": same * float("nan"), "reference": same})
