"""The engine's promises, on the smallest task it runs (tests/toy_task.py), not through a whole method: exact
resume, one metrics row per step across a kill, best.pt by the monitored metric and its mode, a NaN stop that keeps
the last good checkpoint, atomic checkpoint writes."""

from __future__ import annotations

import json

import pytest
import torch
from geoloc.engine import NonFiniteLossError, Task, Trainer, TrainerConfig, seed_everything
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine.sampling import item_rng, split_key

from helpers.kill import run_killed_at
from toy_task import Points, ScriptedRecall


class NoisyLine(Task):
    """A line fitted to noisy points: the noise comes from torch's RNG in the step and the data's per-item RNG, so a
    resume reproduces the run only if the engine restores every RNG, the optimizer and the epoch exactly."""

    monitor = "error"

    def __init__(self):
        super().__init__()
        self.line = torch.nn.Linear(1, 1)

    def configure_optimizers(self):
        opt = torch.optim.Adam(self.parameters(), lr=0.05)
        return [opt], [torch.optim.lr_scheduler.StepLR(opt, step_size=1, gamma=0.9)]

    def training_step(self, batch, engine):
        noise = 0.01 * torch.randn_like(batch["y"])
        return {"loss": ((self.line(batch["x"]) - batch["y"] - noise) ** 2).mean()}

    def validation_step(self, batch):
        return {"error": (self.line(batch["x"]) - batch["y"]).abs().squeeze(1), "index": batch["index"]}

    def validation_epoch_end(self, outputs):
        return {"error": float(outputs["error"].mean())}


class NoisyPoints(torch.utils.data.Dataset):
    def __len__(self):
        return 12

    def __getitem__(self, key):
        index, _ = split_key(key)
        jitter = float(item_rng(0, key).normal(0, 0.1))  # keyed on (seed, epoch, index): the same after a resume
        x = torch.tensor([index / 12.0])
        return {"x": x, "y": 2 * x + 1 + jitter, "index": index}


def config(**kw) -> TrainerConfig:
    return TrainerConfig(**{"max_epochs": 4, "num_workers": 0, "device": "cpu", "progress": False,
                            "persistent_workers": False, "monitor_mode": "min", **kw})


def fit(run_dir, **kw):
    seed_everything(0)
    task = NoisyLine()
    best = Trainer(config(**kw.pop("trainer", {})), run_dir).fit(task, NoisyPoints(), NoisyPoints(), batch_size=4,
                                                                 **kw)
    return task, best


def rows(run_dir):
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def killed_at(run_dir, step, monkeypatch):
    """fit(), killed (KeyboardInterrupt) as global step `step` starts."""
    run_killed_at(NoisyLine, step, lambda: fit(run_dir), monkeypatch)


def test_kill_and_resume_reproduce_the_uninterrupted_run_bit_for_bit(tmp_path, monkeypatch):
    full, _ = fit(tmp_path / "full")
    killed_at(tmp_path / "run", step=5, monkeypatch=monkeypatch)  # in the second epoch (3 steps each)
    assert ckpt_io.load(tmp_path / "run" / "last.pt")["epoch"] == 0
    resumed, _ = fit(tmp_path / "run", resume=tmp_path / "run" / "last.pt")
    for (name, a), (_, b) in zip(full.state_dict().items(), resumed.state_dict().items()):
        assert torch.equal(a, b), name
    a, b = ckpt_io.load(tmp_path / "full" / "last.pt"), ckpt_io.load(tmp_path / "run" / "last.pt")
    assert a["optimizers"][0]["state"][0]["exp_avg"].equal(b["optimizers"][0]["state"][0]["exp_avg"])
    assert a["schedulers"] == b["schedulers"] and a["global_step"] == b["global_step"] == 12
    # one row per step, as if never killed: the killed run's rows after its checkpoint are gone
    strip = lambda rs: [{k: v for k, v in r.items() if k not in ("time", "train/epoch_samples_per_s")}  # noqa: E731
                        for r in rs]
    assert strip(rows(tmp_path / "run")) == strip(rows(tmp_path / "full"))


def test_a_line_cut_by_a_kill_is_dropped_on_resume(tmp_path, monkeypatch):
    killed_at(tmp_path / "run", step=4, monkeypatch=monkeypatch)
    with open(tmp_path / "run" / "metrics.jsonl", "a") as f:
        f.write('{"step": 4, "train/lo')  # the kill arrived mid-line
    fit(tmp_path / "run", resume=tmp_path / "run" / "last.pt")
    assert all(isinstance(r, dict) for r in rows(tmp_path / "run"))
    steps = [r["step"] for r in rows(tmp_path / "run") if "train/epoch_epoch" in r]
    assert steps == [3, 6, 9, 12]


def test_best_follows_the_monitored_metric_and_its_mode(tmp_path):
    """ScriptedRecall reports R@1 = 0.2, 0.6, 0.4: best.pt is epoch 1 for max, epoch 0 for min; the log says by
    which metric and mode best.pt was chosen, once."""
    for mode, epoch in (("max", 1), ("min", 0)):
        run_dir = tmp_path / mode
        best = Trainer(config(max_epochs=3, monitor_mode=mode), run_dir).fit(
            ScriptedRecall([0.2, 0.6, 0.4]), Points(), Points(), batch_size=2)
        assert best["epoch"] == epoch and ckpt_io.load(run_dir / "best.pt")["epoch"] == epoch
        assert [r for r in rows(run_dir) if "run/monitor" in r] == [
            {"step": 0, "time": rows(run_dir)[0]["time"], "run/monitor": "R@1", "run/monitor_mode": mode}]


def test_a_task_that_names_no_metric_is_told_how_to_fix_it(tmp_path):
    class Unnamed(ScriptedRecall):
        monitor = None

    with pytest.raises(ValueError, match="names no validation metric.*trainer.monitor="):
        Trainer(config(), tmp_path).fit(Unnamed([0.1] * 4), Points(), Points(), batch_size=2)


def test_a_nan_loss_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path, monkeypatch):
    original = NoisyLine.training_step

    def nan_in_epoch_1(self, batch, engine):
        out = original(self, batch, engine)
        if engine.epoch == 1:
            out["loss"] = out["loss"] * float("nan")
        return out

    monkeypatch.setattr(NoisyLine, "training_step", nan_in_epoch_1)
    with pytest.raises(NonFiniteLossError, match="loss is nan at epoch 1"):
        fit(tmp_path)
    state = ckpt_io.load(tmp_path / "last.pt")
    assert state["epoch"] == 0 and all(torch.isfinite(v).all() for v in state["task"].values())


def test_checkpoint_write_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "last.pt"
    ckpt_io.save_atomic({"task": {"x": torch.ones(3)}}, path)

    def broken_save(obj, f):
        f.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError):
        ckpt_io.save_atomic({"task": {"x": torch.zeros(3)}}, path)
    assert torch.equal(ckpt_io.load(path)["task"]["x"], torch.ones(3))  # the old file is intact
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]  # no temp file left behind
