"""A checkpoint keeps the MSAE it was trained with: one whose config does not name head.scale_activation (every
checkpoint written before the option, of either layout) is rebuilt with the branches' ReLU."""

from __future__ import annotations

import pytest
import torch
from geoloc.engine import checkpoint as ckpt_io
from geoloc.tasks.crossview.crossview_run import restored_task, stored_config
from omegaconf import OmegaConf


def _with_head(state: dict, **head) -> dict:
    cfg = OmegaConf.create(state["config"])
    section = {k: v for k, v in OmegaConf.to_container(cfg.head).items() if k != "scale_activation"}
    cfg.head = {**section, **head}
    return {**state, "config": OmegaConf.to_yaml(cfg)}


@pytest.mark.slow
def test_a_checkpoint_without_the_key_keeps_the_relu(finished_run):
    _, run_dir = finished_run
    state = ckpt_io.load(run_dir / "best.pt")
    assert OmegaConf.create(state["config"]).head.scale_activation == "none"  # TINY runs head=msae: the paper's
    x = torch.randn(2, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    masks = {}
    for name, head in (("old", {}), ("relu", {"scale_activation": "relu"}), ("none", {"scale_activation": "none"})):
        edited = _with_head(state, **head)
        stored = stored_config(edited)
        task = restored_task(edited, run_dir / "best.pt", stored)
        branch = task.model.eval().query
        masks[name] = branch(x, return_attention=True)[1]
        if name == "old":
            assert "scale_activation" not in stored.head and branch.head.scale_activation == "relu"
    assert torch.equal(masks["old"], masks["relu"])
    assert (masks["old"] - masks["none"]).abs().max() > 1e-4  # the same weights read as eq. 3 give another mask
