"""Resume is exact or refused: ckpt= only with the stored config, init_from= for a new run from a checkpoint's
weights, shape mismatches that name the checkpoint and keys, and one metrics row per step across a resume."""

from __future__ import annotations

import hashlib
import json
import shutil

import pytest
import torch
from omegaconf import OmegaConf
from geoloc.config import ConfigError
from geoloc.engine import checkpoint as ckpt_io
from geoloc.launch import resume, run
from geoloc.tasks.crossview.crossview_run import INIT_FROM_FRESH

from helpers.crossview_runs import train_cfg, task_of


def test_config_differences_skip_only_the_allow_list():
    stored = {"optim": {"lr": 1e-4, "betas": [0.9, 0.999]}, "trainer": {"max_epochs": 1, "precision": "32"},
              "dataset": {"root": "/a", "workers": 2}, "run_dir": "/r1", "old": 1}
    requested = {"optim": {"lr": 1e-2, "betas": [0.9, 0.99]}, "trainer": {"max_epochs": 9, "precision": "32"},
                 "dataset": {"root": "/b", "workers": 8}, "run_dir": "/r2", "new": {"k": 2}}
    allowed = resume.RESUME_MAY_CHANGE + ("dataset.workers",)  # a task's own allow-list adds to the engine's
    assert resume.config_differences(stored, requested, allowed) == [
        "dataset.root: /a → /b", "new.k: (absent) → 2", "old: 1 → (absent)",
        "optim.betas: [0.9, 0.999] → [0.9, 0.99]", "optim.lr: 0.0001 → 0.01"]
    assert resume.config_differences(stored, stored, allowed) == []
    assert resume.config_differences(stored, requested)[0] == "dataset.root: /a → /b"
    assert "dataset.workers: 2 → 8" in resume.config_differences(stored, requested)  # not allowed without the task


def test_resume_with_a_changed_lr_or_dataset_root_is_refused_with_the_differences(finished_run, tmp_path):
    root, finished = finished_run
    other = tmp_path / "other"
    with pytest.raises(ConfigError, match="resumes the run with the config stored in it") as err:
        run.train(train_cfg(root, tmp_path / "resumed", "trainer.max_epochs=2", f"ckpt={finished / 'last.pt'}",
                            "optim.lr=0.01", f"dataset.root={other}"))
    message = str(err.value)
    assert "optim.lr: 0.0001 → 0.01" in message and f"dataset.root: {root} → {other}" in message
    assert "trainer.max_epochs" not in message.split("A resume may change only")[0]  # allowed, so not listed
    assert f"init_from={finished / 'last.pt'}" in message
    assert not (tmp_path / "resumed").exists()  # refused before writing anything


def test_resume_may_add_epochs_and_change_how_it_is_shown(finished_run, tmp_path):
    root, finished = finished_run
    run.train(train_cfg(root, tmp_path / "resumed", f"ckpt={finished / 'last.pt'}", "trainer.max_epochs=2",
                        "trainer.progress=true", "trainer.log_every_n_steps=1", "trainer.pin_memory=false"))
    state = ckpt_io.load(tmp_path / "resumed" / "last.pt")
    assert state["epoch"] == 1 and state["global_step"] == 6  # 3 steps per epoch, continued from epoch 0


def compose_as_hydra(overrides):
    """A composed train config that records its command line, as Hydra does for train.py."""
    from hydra import compose, initialize_config_dir

    from conftest import CONF

    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("train", overrides=overrides, return_hydra_config=True)


def test_the_readme_resume_command_works_for_a_run_made_with_overrides(finished_run, tmp_path):
    """`python train.py ckpt=RUN/last.pt hydra.run.dir=RUN trainer.max_epochs=N`, as the README writes it: the
    overrides the run was made with are not repeated, and the run goes on with the stored config."""
    root, finished = finished_run
    resumed = tmp_path / "resumed"
    shutil.copytree(finished, resumed)
    run.train(compose_as_hydra([f"ckpt={resumed / 'last.pt'}", f"run_dir={resumed}", "trainer.max_epochs=2"]))
    state = ckpt_io.load(resumed / "last.pt")
    assert state["epoch"] == 1 and state["global_step"] == 6
    stored = OmegaConf.create(state["config"])
    assert stored.dataset.name == "cvusa" and stored.dataset.root == str(root)  # not the default synthetic data
    assert stored.trainer.max_epochs == 2 and stored.model.dim == 16


def test_a_key_the_command_line_changes_is_refused_by_name_and_only_it(finished_run, tmp_path):
    root, finished = finished_run
    with pytest.raises(ConfigError, match="resumes the run with the config stored in it") as err:
        run.train(compose_as_hydra([f"ckpt={finished / 'last.pt'}", f"run_dir={tmp_path / 'r'}", "optim.lr=0.01"]))
    listed = str(err.value).split("(stored → requested):")[1].split("Drop those")[0]
    assert listed.strip() == "optim.lr: 0.0001 → 0.01"  # not the dataset, network... the command line left out
    assert not (tmp_path / "r").exists()


@pytest.mark.slow
def test_a_resume_in_place_from_an_older_checkpoint_is_refused_unless_asked_for(tiny_cvusa, tmp_path):
    """ckpt=RUN/best.pt hydra.run.dir=RUN would rewind last.pt and metrics.jsonl to best.pt's epoch."""
    run_dir = tmp_path / "run"
    run.train(train_cfg(tiny_cvusa, run_dir, "trainer.max_epochs=2"))
    older = run_dir / "epoch0.pt"
    state = ckpt_io.load(run_dir / "last.pt")
    ckpt_io.save_atomic({**state, "epoch": 0}, older)
    rows = (run_dir / "metrics.jsonl").read_text()
    with pytest.raises(ConfigError, match=r"epoch 0, but .*last.pt in the run dir .* is from epoch 1.*rewind=true"):
        run.train(train_cfg(tiny_cvusa, run_dir, "trainer.max_epochs=2", f"ckpt={older}"))
    assert (run_dir / "metrics.jsonl").read_text() == rows and ckpt_io.load(run_dir / "last.pt")["epoch"] == 1
    run.train(train_cfg(tiny_cvusa, run_dir, "trainer.max_epochs=2", f"ckpt={older}", "rewind=true"))
    assert ckpt_io.load(run_dir / "last.pt")["epoch"] == 1  # epoch 1 trained again, on purpose


@pytest.mark.slow
def test_init_from_starts_a_new_run_from_the_weights_and_records_the_source(finished_run, tmp_path):
    root, finished = finished_run
    source_path = finished / "last.pt"
    source = ckpt_io.load(source_path)
    assert (source["task"]["loss.queue.ids"] >= 0).any()  # the source run filled its GMS queue

    # the weights arrive; the GMS queue (the source data's places) starts empty
    cfg = train_cfg(root, tmp_path / "x")
    task = task_of(cfg)
    record = ckpt_io.init_from(task, source_path, fresh=INIT_FROM_FRESH)
    for key, value in task.state_dict().items():
        if not key.startswith("loss."):
            assert torch.equal(value, source["task"][key]), key
    queue = task.loss.queue
    assert (queue.ids == -1).all() and int(queue.ptr) == 0 and not queue.descriptors.any()
    assert record["sha256"] == hashlib.sha256(source_path.read_bytes()).hexdigest()

    # a whole run: new lr, another queue length, epoch 0, its own best, the source written down
    new = tmp_path / "new"
    run.train(train_cfg(root, new, "trainer.max_epochs=1", "optim.lr=0.01", "loss.queue_size=4",
                        f"init_from={source_path}"))
    state = ckpt_io.load(new / "last.pt")
    assert state["epoch"] == 0 and state["global_step"] == 3
    assert state["optimizers"][0]["param_groups"][0]["lr"] == 0.01
    assert state["best"]["epoch"] == 0
    written = json.loads((new / "init_from.json").read_text())
    assert written == state["init_from"] == {**record, "path": str(source_path.resolve())}
    assert f"init_from: {source_path}" in state["config"]


def test_init_from_and_ckpt_together_are_refused(finished_run, tmp_path):
    root, finished = finished_run
    with pytest.raises(ConfigError, match="Pass one of them"):
        run.train(train_cfg(root, tmp_path / "r", f"ckpt={finished / 'last.pt'}", f"init_from={finished / 'last.pt'}"))


@pytest.mark.slow
def test_a_shape_mismatch_names_the_checkpoint_and_the_keys(finished_run, tmp_path):
    root, finished = finished_run
    with pytest.raises(ConfigError, match="does not match") as err:  # init_from into another network width
        run.train(train_cfg(root, tmp_path / "a", "model.dim=32", f"init_from={finished / 'last.pt'}"))
    assert str(finished / "last.pt") in str(err.value) and "vs model" in str(err.value)

    # resume: a checkpoint whose stored config passes the config check but whose tensors do not fit it
    state = ckpt_io.load(finished / "last.pt")
    state["config"] = state["config"].replace("dim: 16", "dim: 32")
    edited = tmp_path / "edited" / "last.pt"
    ckpt_io.save_atomic(state, edited)
    with pytest.raises(ConfigError, match="does not match") as err:
        run.train(train_cfg(root, tmp_path / "b", "model.dim=32", "trainer.max_epochs=2", f"ckpt={edited}"))
    assert str(edited) in str(err.value) and "vs model" in str(err.value)


def rows(run_dir):
    """metrics.jsonl without the wall-clock columns."""
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(x).items() if k != "time" and "samples_per_s" not in k} for x in lines]
