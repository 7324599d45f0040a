"""Hydra multirun through hydra-submitit-launcher's local executor, the launcher configs, and the sweep table."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import pytest
import yaml
from conftest import CONF, REPO, TINY
from hydra import compose, initialize_config_dir

sys.path.insert(0, str(REPO / "tools"))
import aggregate_sweep  # noqa: E402

needs_submitit = pytest.mark.skipif(importlib.util.find_spec("hydra_plugins.hydra_submitit_launcher") is None,
                                    reason="hydra-submitit-launcher is not installed")


@needs_submitit
def test_local_sweep_runs_two_jobs_and_the_table_gathers_them(tiny_cvusa, tmp_path):
    sweep = tmp_path / "multirun"
    cmd = [sys.executable, str(REPO / "train.py"), "-m", "hydra/launcher=submitit_local", *TINY,
           f"dataset.root={tiny_cvusa}", "trainer.max_epochs=1", "seed=0,1", f"hydra.sweep.dir={sweep}",
           "hydra.sweep.subdir=${hydra.job.num}", "hydra.launcher.timeout_min=5", "hydra.launcher.cpus_per_task=1"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for job in ("0", "1"):
        lines = (sweep / job / "metrics.jsonl").read_text().splitlines()
        assert any('"val/R@1"' in line for line in lines), job
        assert (sweep / job / "last.pt").is_file()
    text = aggregate_sweep.main([str(sweep)])
    assert "| (base) | 2 |" in text  # the two seeds of one setting: one row, mean ± std


@needs_submitit
@pytest.mark.parametrize("launcher,target,tasks", [("slurm_gpu", "SlurmLauncher", 4), ("local_cpu", "LocalLauncher", 1),
                                                   ("submitit_slurm", "SlurmLauncher", 1)])
def test_launcher_configs_compose(launcher, target, tasks):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[f"hydra/launcher={launcher}"], return_hydra_config=True)
    assert cfg.hydra.launcher._target_.endswith(target)
    assert cfg.hydra.launcher.tasks_per_node == tasks


def _fake_run(root, name, overrides, records):
    run = root / name
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_aggregate_takes_the_last_validation_and_averages_over_seeds(tmp_path, capsys):
    root = tmp_path / "sweep"
    shared = ["dataset.root=/data/cvusa"]
    for seed, r1 in ((0, 0.5), (1, 0.7)):
        _fake_run(root, f"{seed}_full", [*shared, "ablation=full", f"seed={seed}"], [
            {"step": 1, "val/R@1": 0.0, "val/R@5": 0.1},
            {"step": 2, "train/epoch_loss": 1.0},
            {"step": 3, "val/R@1": r1, "val/R@5": 0.9},  # the last validation counts
            {"step": 3, "train/epoch_loss": 0.5},
        ])
    _fake_run(root, "2_no_gms", [*shared, "ablation=no_gms", "seed=0"], [{"step": 3, "val/R@1": 0.25, "val/R@5": 0.5}])
    _fake_run(root, "3_crashed", [*shared, "ablation=no_msae", "seed=0"], [{"step": 1, "train/loss": 2.0}])

    groups = aggregate_sweep.group(aggregate_sweep.collect(root))
    assert set(groups) == {"ablation=full", "ablation=no_gms"}  # no dataset.root, no seed; no val -> left out
    assert [r["R@1"] for r in groups["ablation=full"]] == [0.5, 0.7]
    text = aggregate_sweep.main([str(root), "--out", str(tmp_path / "table.md")])
    assert "| ablation=full | 2 | 60.00 ± 14.14 | 90.00 ± 0.00 |" in text
    assert "| ablation=no_gms | 1 | 25.00 | 50.00 |" in text
    assert (tmp_path / "table.md").read_text().strip() == text
    assert text.splitlines()[0] == "| run | seeds | R@1 | R@5 |"
