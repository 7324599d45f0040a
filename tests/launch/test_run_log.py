"""A run folder holds the run's own log: what it printed (the epoch lines, the table); an evaluation's folder also
holds its metrics, and localize.py's out= folder is its run folder."""

from __future__ import annotations

import json

from geoloc.launch import run
from geoloc.launch.run_log import run_log
from hydra import compose, initialize_config_dir

from conftest import CONF, compose_evaluate


def test_what_the_block_prints_lands_in_the_log_and_on_the_console(tmp_path, capsys):
    with run_log(tmp_path, "train") as path:
        print("[epoch 0] R@1 0.5")
    print("after the run")
    assert path == tmp_path / "train.log"
    assert path.read_text() == "[epoch 0] R@1 0.5\n"
    assert capsys.readouterr().out == "[epoch 0] R@1 0.5\nafter the run\n"


def test_a_training_and_an_evaluation_log_what_they_printed(finished_run, tmp_path, capsys):
    _, finished = finished_run
    log = (finished / "train.log").read_text()
    assert "[epoch 0]" in log and "| R@1 |" in log  # the epoch line and the final table

    metrics = run.evaluate(compose_evaluate([f"ckpt={finished / 'best.pt'}", "progress=false",
                                             f"run_dir={tmp_path / 'e'}"]))
    assert "| R@1 |" in (tmp_path / "e" / "evaluate.log").read_text()
    assert json.loads((tmp_path / "e" / "metrics.json").read_text()) == metrics


def test_localize_out_is_its_run_folder(tmp_path):
    """out=DIR used to leave an empty outputs/localize/<stamp>/ beside DIR."""
    given = ["ckpt=a", "gallery=b", "image=c"]
    with initialize_config_dir(str(CONF), version_base="1.3"):
        assert compose("localize", [*given, f"out={tmp_path}"], return_hydra_config=True).hydra.run.dir == str(tmp_path)
        default = compose("localize", given, return_hydra_config=True).hydra.run.dir
    assert default.startswith("outputs/localize/")
