"""experiment=vigor_cpu (and vigor_cross_cpu), u1652_cpu and any_view_cpu: each composes as the README says and
trains one tiny epoch end to end (on tiny renders of the same layouts instead of the recipes' medium worlds)."""

from __future__ import annotations

import json

import pytest
import torch
from geoloc import registry
from geoloc.launch import run
from geoloc.synthetic import generate

from conftest import compose_train

QUICK = ["trainer.max_epochs=1", "trainer.val_every_n_epochs=1", "trainer.num_workers=0", "trainer.progress=false",
         "trainer.device=cpu", "figures=false"]


def test_the_recipes_choose_what_they_say():
    vigor = compose_train(["experiment=vigor_cpu"])
    assert (vigor.dataset.name, vigor.dataset.preset, vigor.dataset.alignment) == ("vigor", "vigor_medium", "ipt")
    assert (vigor.loss.name, vigor.sampler.name, vigor.model.shared) == ("infonce", "no_duplicate", True)
    assert (vigor.trainer.max_epochs, vigor.dataset.cache_decoded) == (120, True)  # 11.3 min with the cache
    cross = compose_train(["experiment=vigor_cross_cpu"])  # vigor_cpu on the larger world's cross-area split
    assert (cross.dataset.preset, cross.dataset.setting, cross.trainer.max_epochs) == ("vigor_large", "cross_area", 120)
    assert (cross.dataset.alignment, cross.dataset.camera_height_m) == ("ground", 2.2)  # the renderer's camera
    assert (cross.loss.name, cross.sampler.name, cross.dataset.cache_decoded) == ("infonce", "no_duplicate", True)
    assert cross.optim.weight_decay == 0.1 and vigor.optim.weight_decay == 0.01
    assert (vigor.backbone.name, cross.backbone.name, cross.backbone.width) == ("timm", "vgg16", 0.125)
    assert (cross.backbone.pretrained, cross.backbone.weights_path) == (True, "geoloc:synthetic_vgg16_cpu")
    u1652 = compose_train(["experiment=u1652_cpu"])
    assert (u1652.dataset.name, u1652.dataset.preset, u1652.dataset.alignment) == ("u1652", "u1652_medium", "none")
    assert (u1652.loss.name, u1652.sampler.name, u1652.dataset.aerial_rotation_deg) == ("infonce", "no_duplicate", 90)
    any_view = compose_train(["experiment=any_view_cpu"])
    assert (any_view.views.name, any_view.views.fov_min, any_view.views.fov_max) == ("any_view", 70.0, 360.0)
    assert (any_view.loss.name, any_view.dataset.alignment, any_view.dataset.random_heading) == (
        "any_view_infonce", "ipt", True)
    assert compose_train([]).views.name == "single"  # the default run has one query view


def test_the_cross_area_recipe_starts_from_the_shipped_trunk():
    """vigor_cross_cpu's one shared network starts from geoloc:synthetic_vgg16_cpu, tensor for tensor, where
    vigor_cpu's ConvNeXt starts from a random draw."""
    from geoloc.models import packaged_weights

    shipped = torch.load(packaged_weights.packaged_file("geoloc:synthetic_vgg16_cpu", "vgg16"), map_location="cpu",
                         weights_only=True)
    trunk = registry.build("backbone", compose_train(["experiment=vigor_cross_cpu"]).backbone).state_dict()
    assert set(trunk) == set(shipped) and all(torch.equal(trunk[k], shipped[k]) for k in shipped)


def last_validation(run_dir) -> dict:
    lines = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines() if '"val/R@1"' in x]
    return lines[-1]


@pytest.mark.slow
def test_vigor_cpu_trains_a_tiny_epoch(tmp_path):
    root = generate("vigor", tmp_path / "vigor", seed=3, preset="vigor_tiny", train=6, val=3, progress=False)
    cfg = compose_train(["experiment=vigor_cpu", f"dataset.root={root}", "dataset.batch_size=4",
                         "dataset.cities=[Chicago,NewYork]",  # vigor_tiny renders two cities
                         f"run_dir={tmp_path / 'run'}", *QUICK])
    run.train(cfg)
    assert {"val/R@1", "val/hit_rate"} <= set(last_validation(tmp_path / "run"))


@pytest.mark.slow
def test_u1652_cpu_trains_a_tiny_epoch(tmp_path):
    root = generate("u1652", tmp_path / "u1652", seed=1, preset="u1652_tiny", train=5, val=2, progress=False)
    cfg = compose_train(["experiment=u1652_cpu", f"dataset.root={root}", "dataset.batch_size=4",
                         f"run_dir={tmp_path / 'run'}", *QUICK])
    run.train(cfg)
    assert {"val/R@1", "val/AP"} <= set(last_validation(tmp_path / "run"))


@pytest.mark.slow
def test_any_view_cpu_trains_a_tiny_epoch(tiny_cvusa, tmp_path):
    cfg = compose_train(["experiment=any_view_cpu", "dataset=cvusa", f"dataset.root={tiny_cvusa}",
                         "dataset.batch_size=4", "dataset.heading_steps=4", f"run_dir={tmp_path / 'run'}", *QUICK])
    run.train(cfg)
    record = last_validation(tmp_path / "run")
    assert {"val/R@1", "val/heading_median_deg"} <= set(record)
