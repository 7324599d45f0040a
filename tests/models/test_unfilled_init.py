"""unfilled_init: a network built to be loaded draws no random weight, and the checkpoint's weights are all it has."""

from __future__ import annotations

import pytest
import torch
from geoloc.engine import checkpoint as ckpt_io
from geoloc.models.unfilled_init import RANDOM_FILLS, unfilled_init
from geoloc.models.vgg import VGG16Trunk
from geoloc.tasks.crossview.crossview_run import build_run, restored_task, stored_config
from torch.nn import init

from conftest import TINY, compose_train


def test_no_fill_draws_and_the_fills_come_back_after_an_error():
    fills = {name: getattr(init, name) for name in RANDOM_FILLS}
    torch.manual_seed(0)
    before = torch.get_rng_state()
    with unfilled_init():
        VGG16Trunk(width=0.125, batchnorm=True)
        torch.nn.Linear(64, 64)
    assert torch.equal(torch.get_rng_state(), before)  # nothing drawn: the generator is where it was
    VGG16Trunk(width=0.125, batchnorm=True)
    assert not torch.equal(torch.get_rng_state(), before)  # outside it the trunk draws, as training needs
    with pytest.raises(RuntimeError, match="inside"):
        with unfilled_init():
            raise RuntimeError("inside")
    assert {name: getattr(init, name) for name in RANDOM_FILLS} == fills


def test_a_restored_task_draws_nothing_and_holds_exactly_the_checkpoints_weights(finished_run):
    _, run_dir = finished_run
    state = ckpt_io.load(run_dir / "best.pt")
    torch.manual_seed(1)
    before = torch.get_rng_state()
    task = restored_task(state, run_dir / "best.pt", stored_config(state))
    assert torch.equal(torch.get_rng_state(), before)  # built under unfilled_init (evaluate.py, the apps, bench)
    own = task.state_dict()
    assert own.keys() == state["task"].keys()
    for key, value in state["task"].items():
        assert torch.equal(own[key], value), key


def test_a_resume_builds_its_task_without_drawing_where_a_fresh_run_draws(finished_run, tmp_path, monkeypatch):
    root, run_dir = finished_run
    common = [*TINY, f"dataset.root={root}", "trainer.max_epochs=2"]
    counts = fills_counted(monkeypatch)
    drawn = {}
    for name, extra in (("fresh", []), ("resumed", [f"ckpt={run_dir / 'last.pt'}"])):
        before, torch_state = sum(counts.values()), torch.manual_seed(0).get_state()  # build_run seeds 0 too
        build_run(compose_train([*common, f"run_dir={tmp_path / name}", *extra]), tmp_path / name)
        drawn[name] = sum(counts.values()) - before
        assert torch.equal(torch.get_rng_state(), torch_state) == (name == "resumed"), name
    assert drawn["fresh"] > 0 and drawn["resumed"] == 0  # the checkpoint will replace every weight


def fills_counted(monkeypatch) -> dict:
    """{fill: calls} of torch.nn.init's random fills from now on (a fill that unfilled_init turns off never
    counts); monkeypatch puts the fills back after the test."""
    counts = dict.fromkeys(RANDOM_FILLS, 0)
    for name in RANDOM_FILLS:
        def call(*args, _name=name, _fill=getattr(init, name), **kwargs):
            counts[_name] += 1
            return _fill(*args, **kwargs)
        monkeypatch.setattr(init, name, call)
    return counts
