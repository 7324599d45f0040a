"""trainer.monitor is checked against the keys validation reports, at the start of a run: from the config alone at
the parse (a misspelt name, or a refiner's key without a refiner), and on the validation split once it is read (a
key that split does not give), before anything is written, so the run's folder is left free for the corrected run.
MMDIP's phases each monitor their own metric, and trainer.monitor is refused for it."""

from __future__ import annotations

import pytest
from geoloc.config import ConfigError
from geoloc.launch import run
from geoloc.tasks.crossview.crossview_config import parse_training

from conftest import TINY, compose_train
from helpers.crossview_runs import train_cfg

UNKNOWN = "is not a metric that validation reports"
# the refinement recipes on the tiny VIGOR (TINY names cvusa, which would take the recipes' vigor settings)
REFINE = ["experiment=refine_vigor", "dataset=vigor", "dataset.preset=vigor_tiny"]
REFINE_UNKNOWN = ["experiment=refine_vigor_unknown_heading", "dataset=vigor", "dataset.preset=vigor_tiny"]


@pytest.mark.parametrize("recipe, monitor", [
    ([], "R@l"),  # an ell for a one
    ([*REFINE], "fine_median"),
    ([*REFINE_UNKNOWN], "fine_heading_median"),  # found after 15 epochs before
    ([], "fine_median_m"),  # a refiner's key, without a refiner
    (["dataset.random_heading=true"], "median_m"),  # the heading search reports recall and heading errors
])
def test_a_monitor_no_validation_reports_is_refused_at_the_parse(recipe, monitor):
    with pytest.raises(ConfigError, match=rf"trainer.monitor='{monitor}' {UNKNOWN} under this config: it reports "
                                          r"R@1, R@5, R@10, R@1%"):
        parse_training(compose_train([*TINY, "run_dir=unused", *recipe, f"trainer.monitor={monitor}"]))


@pytest.mark.parametrize("recipe, monitor", [
    ([], None), ([], "R@1%"), ([], "median_m"), ([], "reference_spread"),
    ([*REFINE], "fine_median_m"), ([*REFINE], "whole_tile_median_m"),
    ([*REFINE_UNKNOWN], "fine_heading_median_deg"),
    (["dataset.random_heading=true"], "heading_median_deg"),
])
def test_every_key_validation_reports_is_accepted(recipe, monitor):
    chosen = [f"trainer.monitor={monitor}"] if monitor else []
    assert parse_training(compose_train([*TINY, "run_dir=unused", *recipe, *chosen])).monitor == (monitor or "R@1")


def test_a_misspelt_or_absent_monitor_fails_before_the_run_writes_and_the_corrected_run_uses_the_folder(
        tiny_cvusa, tmp_path):
    run_dir = tmp_path / "run"
    with pytest.raises(ConfigError, match=f"trainer.monitor='R@l' {UNKNOWN} under this config"):
        run.train(train_cfg(tiny_cvusa, run_dir, "trainer.monitor=R@l"))
    assert not run_dir.exists()
    # a key of another split's plan: CVUSA's pairs have no semi-positives, hence no hit rate; found once the split
    # is read, before the first epoch
    with pytest.raises(ConfigError, match=f"trainer.monitor='hit_rate' {UNKNOWN} on cvusa/val: it reports "
                                          r"R@1, R@5, R@10, R@1%, reference_spread\."):
        run.train(train_cfg(tiny_cvusa, run_dir, "trainer.monitor=hit_rate"))
    assert not run_dir.exists()
    best = run.train(train_cfg(tiny_cvusa, run_dir, "trainer.monitor=R@1", "trainer.max_epochs=1"))
    assert "R@1" in best and (run_dir / "best.pt").is_file()


@pytest.mark.parametrize("trainer", [["trainer.monitor=MIoU"], ["trainer.monitor_mode=min"]])
def test_mmdip_refuses_a_monitor_for_both_phases_before_anything(trainer, tmp_path):
    run_dir = tmp_path / "run"
    with pytest.raises(ConfigError, match=r"task=mmdip selects each phase's best.pt by its own metric, the higher the "
                                          r"better \(phase 1: MIoU, phase 2: SSIM\)"):
        run.train(compose_train(["task=mmdip", f"run_dir={run_dir}", *trainer]))
    assert not run_dir.exists()
