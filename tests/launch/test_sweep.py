"""Hydra multirun through hydra-submitit-launcher's local executor, the launcher configs, and the sweep table."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import pytest
import yaml
from geoloc.engine import Trainer, TrainerConfig
from hydra import compose, initialize_config_dir

from conftest import CONF, REPO, TINY
from toy_task import Points, ScriptedRecall

sys.path.insert(0, str(REPO / "tools"))
import aggregate_sweep  # noqa: E402

needs_submitit = pytest.mark.skipif(importlib.util.find_spec("hydra_plugins.hydra_submitit_launcher") is None,
                                    reason="hydra-submitit-launcher is not installed")


@pytest.mark.slow
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
    text = aggregate_sweep.main([str(root), "--at", "last", "--out", str(tmp_path / "table.md")])
    # epoch: the full runs' last validation ends their second epoch (1); no_gms stopped before its epoch row (0)
    assert "| ablation=full | 2 | 1.00 ± 0.00 | 60.00 ± 14.14 | 90.00 ± 0.00 |" in text
    assert "| ablation=no_gms | 1 | 0.00 | 25.00 | 50.00 |" in text
    assert (tmp_path / "table.md").read_text().strip() == text
    assert text.splitlines()[0] == "| run | seeds | epoch | R@1 | R@5 |"


def _epochs(rows, monitor=("R@1", "max")):
    """metrics.jsonl rows as the trainer writes them: the monitored metric, then per epoch a step row, the
    validation row (when given) and the end-of-epoch row. `rows` is [(epoch, R@1, R@5) or (epoch, None, None) for
    an epoch without validation]."""
    out = [{"step": 10 * rows[0][0], "time": 0.0, "run/monitor": monitor[0], "run/monitor_mode": monitor[1]}]
    for epoch, r1, r5 in rows:
        step = 10 * (epoch + 1)
        out.append({"step": step, "time": 0.0, "train/loss": 0.7, "train/lr": 1e-3})
        if r1 is not None:
            out.append({"step": step, "time": 0.0, "val/R@1": r1, "val/R@5": r5, "val/reference_spread": 1.0})
        out.append({"step": step, "time": 0.0, "train/epoch_loss": 0.7, "train/epoch_samples_per_s": 100.0,
                    "train/epoch_epoch": epoch})
    return out


def _three_seeds(root):
    for seed, rows in ((0, [(0, .10, .5), (1, .40, .8), (2, .30, .7), (3, .35, .9)]),
                       (1, [(0, .20, .6), (1, .50, .7), (2, .50, .95), (3, .45, .9)])):  # a tie: epoch 1 counts
        _fake_run(root, f"{seed}", ["ablation=full", f"seed={seed}"], _epochs(rows))
    # seed 2 validates every 2nd epoch and was killed after validating epoch 3 (0.90, never checkpointed);
    # the resumed run redid epoch 3 and validated it at 0.60
    killed = _epochs([(0, None, None), (1, .20, .65), (2, None, None)])
    killed.append({"step": 40, "time": 0.0, "val/R@1": .90, "val/R@5": .99})
    _fake_run(root, "2", ["ablation=full", "seed=2"], killed + _epochs([(3, .60, .75)]))


def test_validations_pair_each_record_with_its_epoch(tmp_path):
    _three_seeds(tmp_path)
    records = aggregate_sweep.validations(tmp_path / "2" / "metrics.jsonl")
    assert [(r["epoch"], r["R@1"]) for r in records] == [(1, .20), (3, .60)]  # the killed attempt's 0.90 is gone
    assert aggregate_sweep.pick(records, "best", "R@1")["epoch"] == 3
    assert aggregate_sweep.pick(records, "best", "R@1", mode="min")["epoch"] == 1
    tied = aggregate_sweep.validations(tmp_path / "1" / "metrics.jsonl")
    assert aggregate_sweep.pick(tied, "best", "R@1")["epoch"] == 1  # the earliest of equal R@1, as the trainer keeps
    # a run resumed with ckpt= logs into a new run dir from the epoch after the checkpoint's
    _fake_run(tmp_path, "resumed", ["seed=0"], _epochs([(4, .30, .70), (5, .20, .60)]))
    resumed = aggregate_sweep.validations(tmp_path / "resumed" / "metrics.jsonl")
    assert [(r["epoch"], r["R@1"]) for r in resumed] == [(4, .30), (5, .20)]


def test_the_trainers_own_metrics_file_gives_each_validation_its_epoch(tmp_path):
    cfg = TrainerConfig(max_epochs=5, val_every_n_epochs=2, num_workers=0, device="cpu", progress=False,
                        persistent_workers=False)
    best = Trainer(cfg, tmp_path).fit(ScriptedRecall([0.2, 0.6, 0.4]), Points(), Points(), batch_size=2)
    records = aggregate_sweep.validations(tmp_path / "metrics.jsonl")
    assert [(r["epoch"], r["R@1"]) for r in records] == [(1, 0.2), (3, 0.6), (4, 0.4)]  # every 2nd epoch and the last
    assert aggregate_sweep.recorded_monitor(tmp_path / "metrics.jsonl") == ("R@1", "max")
    assert aggregate_sweep.pick(records, "best", "R@1")["epoch"] == best["epoch"] == 3


def test_both_tables_last_and_best_epoch_against_hand_computed_figures(tmp_path):
    _three_seeds(tmp_path / "sweep")
    text = aggregate_sweep.main([str(tmp_path / "sweep")])  # --at both is the default
    last, best = text.split("\n\n### ")
    assert last.splitlines()[0] == "### last epoch"
    # last: epochs 3, 3, 3; R@1 .35 .45 .60: 46.67 ± sqrt(((-11.67)² + (-1.67)² + 13.33²) / 2) = 12.58 (sample std);
    # R@5 .90 .90 .75: 85.00 ± sqrt((25 + 25 + 100) / 2) = 8.66
    assert "| (base) | 3 | 3.00 ± 0.00 | 46.67 ± 12.58 | 85.00 ± 8.66 |" in last
    assert best.splitlines()[0] == "best epoch (highest R@1 of each run)"
    # best: epochs 1, 1, 3: 1.67 ± sqrt((0.44 + 0.44 + 1.78) / 2) = 1.15; R@1 .40 .50 .60: 50.00 ± 10.00;
    # R@5 .80 .70 .75: 75.00 ± 5.00
    assert "| (base) | 3 | 1.67 ± 1.15 | 50.00 ± 10.00 | 75.00 ± 5.00 |" in best
    assert best.splitlines()[2] == "| run | seeds | epoch | R@1 | R@5 |"
    only_best = aggregate_sweep.main([str(tmp_path / "sweep"), "--at", "best", "--metrics", "R@1"])
    assert only_best.splitlines() == ["| run | seeds | epoch | R@1 |", "|---|---|---|---|",
                                      "| (base) | 3 | 1.67 ± 1.15 | 50.00 ± 10.00 |"]


def test_the_best_epoch_follows_the_metric_and_mode_each_run_monitored(tmp_path):
    """A run that selected best.pt by the lowest loss is tabled at that epoch, not at its highest R@1."""
    _fake_run(tmp_path, "0", ["seed=0"], _epochs([(0, .10, .5), (1, .40, .8)], monitor=("R@5", "min")))
    best = aggregate_sweep.main([str(tmp_path), "--at", "best", "--metrics", "R@1"])
    assert best.splitlines()[2] == "| (base) | 1 | 0.00 | 10.00 |"
    assert aggregate_sweep.main([str(tmp_path), "--at", "best", "--monitor", "R@1", "--metrics", "R@1"]
                                ).splitlines()[2] == "| (base) | 1 | 1.00 | 40.00 |"


def _refining_run(root, monitor=("R@1", "max")):
    """A run that logs recall, the refiner's fine_median_m (metres: lower is better) and a plug-in's score of no
    stated direction at epochs 0, 1, 2."""
    records = _epochs([(0, .10, .5), (1, .40, .8), (2, .20, .6)], monitor=monitor)
    errors = iter([3.0, 9.0, 5.0])
    for record in records:
        if "val/R@1" in record:
            record.update({"val/fine_median_m": next(errors), "val/plugin_score": 0.5})
    _fake_run(root, "0", ["seed=0"], records)


def test_a_monitor_from_the_command_line_is_picked_in_its_direction_and_the_title_says_which(tmp_path):
    """--monitor fine_median_m picked the highest error as best, and --at both titled it "highest"."""
    _refining_run(tmp_path / "a")
    best = aggregate_sweep.main([str(tmp_path / "a"), "--monitor", "fine_median_m", "--metrics", "fine_median_m"])
    table = best.split("### ")[2].splitlines()
    assert table[0] == "best epoch (lowest fine_median_m of each run)"  # geoloc's metric: metres, lower is better
    assert table[4] == "| (base) | 1 | 0.00 | 3.00 |"
    assert aggregate_sweep.main([str(tmp_path / "a"), "--at", "best", "--monitor", "fine_median_m",
                                 "--monitor-mode", "max", "--metrics", "fine_median_m"]
                                ).splitlines()[2] == "| (base) | 1 | 1.00 | 9.00 |"  # as asked
    _refining_run(tmp_path / "b", monitor=("fine_median_m", "min"))  # the run's own monitor and mode
    assert aggregate_sweep.main([str(tmp_path / "b"), "--metrics", "fine_median_m"]).split("### ")[2].startswith(
        "best epoch (lowest fine_median_m of each run)")
    assert "best epoch (highest R@1 of each run)" in aggregate_sweep.main([str(tmp_path / "b"), "--monitor", "R@1"])
    with pytest.raises(ValueError, match=r"--monitor plugin_score: whether higher or lower is better .*--monitor-mode"):
        aggregate_sweep.main([str(tmp_path / "b"), "--at", "best", "--monitor", "plugin_score"])
    with pytest.raises(SystemExit):
        aggregate_sweep.main([str(tmp_path / "b"), "--monitor-mode", "min"])  # without --monitor


def test_best_by_a_metric_the_runs_do_not_log_says_which_keys_they_have(tmp_path):
    _three_seeds(tmp_path)
    with pytest.raises(ValueError, match=r"no val/mAP.*'R@1', 'R@5'.*--monitor"):
        aggregate_sweep.main([str(tmp_path), "--monitor", "mAP"])


@pytest.mark.slow
def test_the_readme_table_2_sweep_runs_every_ablation_row(tiny_cvusa, tmp_path):
    """`python train.py -m ablation=full,no_ipt,no_msae,no_gms` as the README writes it (on tiny data): four jobs,
    each training the row it names, gathered into one table."""
    readme = (REPO / "README.md").read_text()
    assert "python train.py -m ablation=full,no_ipt,no_msae,no_gms" in readme
    sweep = tmp_path / "multirun"
    tiny = [o for o in TINY if not o.startswith("loss.queue_size")]  # the rows set the queue themselves
    cmd = [sys.executable, str(REPO / "train.py"), "-m", "ablation=full,no_ipt,no_msae,no_gms", *tiny,
           f"dataset.root={tiny_cvusa}", "trainer.max_epochs=1", f"hydra.sweep.dir={sweep}",
           "hydra.sweep.subdir=${hydra.job.num}"]
    proc = subprocess.run(cmd, cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    rows = {}
    for job in range(4):
        config = yaml.safe_load((sweep / str(job) / ".hydra" / "config.yaml").read_text())
        assert (sweep / str(job) / "last.pt").is_file()
        rows[job] = (config["dataset"]["alignment"], config["head"]["name"], config["loss"]["queue_size"])
    assert rows == {0: ("ipt", "msae", 1024), 1: ("none", "msae", 1024), 2: ("ipt", "fc", 1024), 3: ("ipt", "msae", 0)}
    text = aggregate_sweep.main([str(sweep)])
    for row in ("ablation=full", "ablation=no_ipt", "ablation=no_msae", "ablation=no_gms"):
        assert f"| {row} | 1 |" in text


def _job(root, name, overrides, max_epochs=4):
    """A sweep job's folder as Hydra writes it before the job runs: .hydra/ with its overrides and config."""
    job = root / name
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (job / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"trainer": {"max_epochs": max_epochs}}))
    return job


def test_failed_and_partial_jobs_are_reported_not_dropped(tmp_path):
    for seed in (0, 1):
        job = _job(tmp_path, str(seed), ["lr=1", f"seed={seed}"])
        (job / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in _epochs(
            [(e, .1 * (e + 1), .5) for e in range(4)])))
    _job(tmp_path, "2", ["lr=1", "seed=2"])  # failed at start-up: Hydra's folder, no metrics
    killed = _job(tmp_path, "3", ["lr=1", "seed=3"])
    text = "".join(json.dumps(r) + "\n" for r in _epochs([(0, .9, .9), (1, .9, .9)]))
    (killed / "metrics.jsonl").write_text(text + '{"step": 30, "val/R@1": 0.')  # killed mid-line, after epoch 1
    out = aggregate_sweep.main([str(tmp_path), "--at", "last"])
    assert "| (base) | 2 |" in out  # the two complete seeds; the killed 0.9 does not enter the mean
    assert f"{tmp_path / '2'}: failed, no metrics.jsonl" in out
    assert f"{tmp_path / '3'}: partial, validated up to epoch 1 of 4 (its last line was cut)" in out


def test_a_damaged_line_names_the_file_and_line(tmp_path):
    job = _job(tmp_path, "0", ["seed=0"])
    good = [json.dumps(r) for r in _epochs([(0, .1, .5), (1, .2, .5)])]
    (job / "metrics.jsonl").write_text("\n".join([good[0], "{not json", *good[1:]]) + "\n")
    with pytest.raises(ValueError, match=rf"{job / 'metrics.jsonl'}:2: not a JSON line"):
        aggregate_sweep.main([str(tmp_path)])


def test_an_mmdip_sweep_is_grouped_by_its_jobs_overrides_and_phase(tmp_path):
    """MMDIP logs into phase1/ and phase2/ below the job's folder, which alone holds .hydra/: two learning rates
    are two rows per phase, never averaged as if they were seeds."""
    for number, (lr, seed) in enumerate([(1e-3, 0), (1e-3, 1), (1e-2, 0), (1e-2, 1)]):
        job = _job(tmp_path, str(number), [f"task.segmentation.lr={lr}", f"seed={seed}"], max_epochs=2)
        for phase, metric in (("phase1", "MIoU"), ("phase2", "SSIM")):
            (job / phase).mkdir()
            records = [{"step": 0, "run/monitor": metric, "run/monitor_mode": "max"}]
            for epoch in range(2):
                records += [{"step": epoch + 1, f"val/{metric}": lr * 100 + seed / 10 + epoch},
                            {"step": epoch + 1, "train/epoch_epoch": epoch}]
            (job / phase / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    out = aggregate_sweep.main([str(tmp_path), "--at", "last"])
    for lr in ("0.001", "0.01"):
        for phase in ("phase1", "phase2"):
            assert f"| task.segmentation.lr={lr} phase={phase} | 2 |" in out
    assert "Not in the tables" not in out


def test_a_sweep_jobs_folder_works_as_a_ckpt_value_on_the_command_line():
    """Hydra's default job folder `0_ablation=no_msae,seed=1` fails as `ckpt=<folder>/last.pt` ("mismatched input
    '='"); geoloc's names parse as they are."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=["ablation=no_msae", "seed=1", "dataset.fov=90"], return_hydra_config=True)
    name = f"0_{cfg.hydra.job.override_dirname}"
    assert name == "0_ablation-no_msae_dataset.fov-90_seed-1"
    parsed = OverridesParser.create().parse_overrides([f"ckpt=multirun/2026-01-01_00-00-00_1/{name}/last.pt"])
    assert parsed[0].value() == f"multirun/2026-01-01_00-00-00_1/{name}/last.pt"


def test_a_sweeper_optimises_the_metric_each_task_names(tmp_path):
    """train.py returns objective(cfg, best): the cross-view run's monitored metric (trainer.monitor, else R@1),
    MMDIP's fused R@1 whatever its phases monitor, and NaN, not 0, when the run did not report it."""
    import math

    from geoloc.launch.run import objective

    from conftest import compose_train

    crossview = compose_train([*TINY, "run_dir=unused"])
    assert objective(crossview, {"R@1": 0.25, "R@5": 0.5}) == 0.25
    refining = compose_train([*TINY, "run_dir=unused", "trainer.monitor=fine_median_m"])
    assert objective(refining, {"R@1": 0.25, "fine_median_m": 3.5}) == 3.5
    mmdip = compose_train(["task=mmdip", "run_dir=unused", "trainer.monitor=SSIM"])
    assert objective(mmdip, {"R@1": 0.75, "phase2": {"SSIM": 0.5}}) == 0.75
    assert math.isnan(objective(crossview, {}))  # nothing reported: no made-up value
