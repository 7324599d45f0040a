"""A run owns its directory: one live run per folder, no run over a finished one, nothing left by a failed start,
checkpoints with the umask's mode, no stale temp files, no silent metrics_out overwrite."""

from __future__ import annotations

import errno
import fcntl
import json
import os
import signal
import stat
import subprocess
import sys
import time

import pytest
import torch
from geoloc.config import ConfigError
from geoloc.engine import checkpoint as ckpt_io
from geoloc.launch import run
from geoloc.launch.rundir import LOCK, RunDirTaken, claimed
from helpers.crossview_runs import train_cfg

from conftest import CONF, REPO, compose_evaluate, compose_train

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}


def hold_in_subprocess(run_dir):
    """A live run: another process that claims `run_dir` and sleeps."""
    code = ("import sys, time; from geoloc.launch.rundir import claimed\n"
            "with claimed(sys.argv[1]):\n    print('held', flush=True); time.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(run_dir)], env=ENV, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_run_is_refused_while_the_first_holds_the_dir_and_a_killed_run_frees_it(tiny_cvusa, tmp_path):
    run_dir = tmp_path / "run"
    holder = hold_in_subprocess(run_dir)
    try:
        (run_dir / ".hydra").mkdir()  # what Hydra wrote for the live run, before it trained
        (run_dir / ".hydra" / "config.yaml").write_text("live run\n")
        with pytest.raises(RunDirTaken, match=rf"in use by another live run \(pid {holder.pid} on "):
            run.train(train_cfg(tiny_cvusa, run_dir))
        # the refused run removed nothing of the live run's (it looks empty, but it is not ours)
        assert (run_dir / ".hydra" / "config.yaml").read_text() == "live run\n"
        assert not (run_dir / "last.pt").exists() and not (run_dir / "metrics.jsonl").exists()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    with claimed(run_dir):  # the OS dropped the killed holder's lock
        assert f"pid {os.getpid()} " in (run_dir / LOCK).read_text()


def test_a_file_system_without_locks_gets_a_clear_error(tmp_path, monkeypatch):
    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with pytest.raises(OSError, match=r"cannot lock run dir .*file system with locks"), claimed(tmp_path / "run"):
        pass


def test_ranks_above_zero_share_rank_zeros_dir_without_claiming_it(tmp_path, monkeypatch):
    # SLURM tasks of one job (hydra/launcher=slurm_gpu) all get the job's run dir; rank 0 holds it
    run_dir = tmp_path / "run"
    holder = hold_in_subprocess(run_dir)
    try:
        monkeypatch.setenv("SLURM_NTASKS", "4")
        monkeypatch.setenv("SLURM_PROCID", "1")
        with claimed(run_dir) as path:
            assert path == run_dir
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()


def test_a_dir_with_a_finished_run_is_refused_unless_ckpt_resumes_it(finished_run, tmp_path):
    root, finished = finished_run
    before = (finished / "last.pt").read_bytes()
    with pytest.raises(RunDirTaken, match="already holds another run's output") as err:
        run.train(train_cfg(root, finished, "trainer.max_epochs=2"))
    message = str(err.value)
    assert f"ckpt={finished / 'last.pt'}" in message and f"hydra.run.dir={finished}" in message
    assert "leave the default" in message
    assert (finished / "last.pt").read_bytes() == before  # untouched
    # an mmdip run's phase checkpoints are protected too (task=mmdip cannot resume at all)
    mmdip_dir = tmp_path / "mmdip"
    (mmdip_dir / "phase1").mkdir(parents=True)
    torch.save({}, mmdip_dir / "phase1" / "best.pt")
    with pytest.raises(RunDirTaken, match=r"phase1/best.pt.*no last.pt to resume"):
        run.train(compose_train(["task=mmdip", f"run_dir={mmdip_dir}"]))


def test_resume_in_place_is_allowed(finished_run, tmp_path):
    root, finished = finished_run
    resumed = tmp_path / "resumed"
    resumed.mkdir()
    for name in ("last.pt", "best.pt", "metrics.jsonl"):
        (resumed / name).write_bytes((finished / name).read_bytes())
    run.train(train_cfg(root, resumed, "trainer.max_epochs=2", f"ckpt={resumed / 'last.pt'}"))
    assert ckpt_io.load(resumed / "last.pt")["epoch"] == 1


@pytest.mark.slow
def test_default_run_dirs_differ_for_runs_started_in_the_same_second(tmp_path):
    # two processes (pids 1111, 2222) resolve Hydra's run and sweep dirs while `now` shows the same second
    script = f"""
import json, os, sys
sys.path.insert(0, {str(REPO)!r})
import train  # registers geoloc's resolvers, as `python train.py` does
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
dirs = []
for pid in (1111, 2222):
    os.getpid = lambda pid=pid: pid
    with initialize_config_dir({str(CONF)!r}, version_base="1.3"):
        OmegaConf.register_new_resolver("now", lambda fmt: "2025-01-01_12-00-00", replace=True)
        cfg = compose("train", return_hydra_config=True)
        dirs.append([OmegaConf.select(cfg, "hydra.run.dir"), OmegaConf.select(cfg, "hydra.sweep.dir")])
print(json.dumps(dirs))
"""
    proc = subprocess.run([sys.executable, "-c", script], env=ENV, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (run_a, sweep_a), (run_b, sweep_b) = json.loads(proc.stdout.splitlines()[-1])
    assert run_a == "outputs/crossview/synthetic/2025-01-01_12-00-00_1111"  # still recognisable
    assert run_b == "outputs/crossview/synthetic/2025-01-01_12-00-00_2222"
    assert sweep_a == "multirun/crossview/2025-01-01_12-00-00_1111" and sweep_b.endswith("_2222")


@pytest.mark.slow
def test_a_run_that_fails_before_writing_leaves_no_dir(finished_run, tiny_cvusa, tmp_path):
    run_dir = tmp_path / "outputs" / "run"
    (run_dir / ".hydra").mkdir(parents=True)  # what Hydra writes before the app starts
    (run_dir / ".hydra" / "config.yaml").write_text("x: 1\n")
    (run_dir / "train.log").write_text("")
    with pytest.raises(ConfigError, match="max_epochs"):
        run.train(train_cfg(tiny_cvusa, run_dir, "trainer.max_epochs=0"))
    assert not run_dir.exists()
    with pytest.raises(ConfigError, match="task=mmdip runs both phases from scratch"):  # mmdip refuses ckpt=
        run.train(compose_train(["task=mmdip", f"run_dir={run_dir}", f"ckpt={tmp_path / 'x.pt'}"]))
    assert not run_dir.exists()
    with pytest.raises(FileNotFoundError):  # not only config errors: a dataset that is not there
        run.train(train_cfg(tmp_path / "nowhere", run_dir))
    assert not run_dir.exists()
    with pytest.raises(FileNotFoundError):  # nor after init_from= loaded its weights
        run.train(train_cfg(tmp_path / "nowhere", run_dir, f"init_from={finished_run[1] / 'last.pt'}"))
    assert not run_dir.exists()


@pytest.mark.slow
def test_train_py_refuses_a_taken_dir_before_hydra_writes_into_it_and_a_config_error_leaves_nothing(tmp_path):
    finished = tmp_path / "finished"
    (finished / ".hydra").mkdir(parents=True)
    (finished / ".hydra" / "overrides.yaml").write_text("- seed=7\n")
    torch.save({}, finished / "last.pt")
    cmd = [sys.executable, str(REPO / "train.py"), "trainer.device=cpu"]
    proc = subprocess.run([*cmd, f"hydra.run.dir={finished}"], cwd=tmp_path, env=ENV, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 1 and "RunDirTaken" in proc.stderr and "ckpt=" in proc.stderr
    assert (finished / ".hydra" / "overrides.yaml").read_text() == "- seed=7\n"  # Hydra did not overwrite it
    assert sorted(p.name for p in finished.iterdir()) == [".hydra", "last.pt"]

    proc = subprocess.run([*cmd, "dataset=cvusa"], cwd=tmp_path, env=ENV, capture_output=True, text=True,
                          timeout=300)  # no dataset.root: a config error
    assert proc.returncode == 1 and "dataset.root" in proc.stderr
    assert not [p for p in (tmp_path / "outputs").rglob("*") if p.is_file() or p.name.startswith("20")]


@pytest.mark.slow
@pytest.mark.parametrize("script", ["evaluate.py", "localize.py"])
def test_evaluate_and_localize_refuse_a_training_runs_folder(script, tmp_path):
    """`evaluate.py ckpt=RUN/best.pt hydra.run.dir=RUN` would have Hydra replace the training's .hydra/ record."""
    finished = tmp_path / "finished"
    (finished / ".hydra").mkdir(parents=True)
    (finished / ".hydra" / "overrides.yaml").write_text("- seed=7\n")
    torch.save({}, finished / "best.pt")
    extra = [f"gallery={tmp_path}", f"image={tmp_path}"] if script == "localize.py" else []
    proc = subprocess.run([sys.executable, str(REPO / script), f"ckpt={finished / 'best.pt'}", *extra,
                           f"hydra.run.dir={finished}"], cwd=tmp_path, env=ENV, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 1 and "belongs to a training run" in proc.stderr, proc.stderr[-2000:]
    assert (finished / ".hydra" / "overrides.yaml").read_text() == "- seed=7\n"
    assert sorted(p.name for p in finished.iterdir()) == [".hydra", "best.pt"]
    with pytest.raises(RunDirTaken, match="belongs to a training"):
        run.evaluate(compose_evaluate([f"ckpt={finished / 'best.pt'}", f"run_dir={finished}"]))


@pytest.mark.parametrize("mask,mode", [(0o022, 0o644), (0o027, 0o640), (0o002, 0o664)], ids=["022", "027", "002"])
def test_checkpoints_get_the_umask_mode(tmp_path, mask, mode):
    before = os.umask(mask)
    try:
        ckpt_io.save_atomic({"x": torch.ones(1)}, tmp_path / "last.pt")
    finally:
        os.umask(before)
    assert stat.S_IMODE((tmp_path / "last.pt").stat().st_mode) == mode


def test_temp_files_of_a_killed_save_are_removed_by_the_next_run_that_owns_the_dir(tmp_path):
    run_dir = tmp_path / "run"
    stale = [run_dir / ".last.pt.k1l2x3.tmp", run_dir / ".best.pt.a8b9.tmp", run_dir / "phase2" / ".last.pt.q.tmp"]
    keep = [run_dir / "last.pt", run_dir / "notes.tmp"]
    holder = hold_in_subprocess(run_dir)
    try:
        for path in stale + keep:  # the live run's saves in progress look just like a killed run's
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(b"x")
        with pytest.raises(RunDirTaken), claimed(run_dir, ckpt=str(run_dir / "last.pt")):
            pass
        assert all(p.exists() for p in stale)  # not ours to clean while another run holds the dir
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    with claimed(run_dir, ckpt=str(run_dir / "last.pt")):
        assert not any(p.exists() for p in stale)
        assert all(p.exists() for p in keep)


def test_metrics_out_is_not_overwritten_unless_asked(finished_run, tmp_path):
    _, finished = finished_run
    out = tmp_path / "metrics.json"
    out.write_text('{"R@1": 0.5}\n')
    for ckpt in (finished / "best.pt", tmp_path / "mmdip" / "phase2" / "best.pt"):  # refused before any loading
        with pytest.raises(ConfigError, match="metrics_out_overwrite=true"):
            run.evaluate(compose_evaluate([f"ckpt={ckpt}", f"metrics_out={out}", "progress=false",
                                           f"run_dir={tmp_path / 'e'}"]))
        assert out.read_text() == '{"R@1": 0.5}\n'
        assert not (tmp_path / "e").exists()  # the refused evaluation left no run dir
    start = time.time()
    run.evaluate(compose_evaluate([f"ckpt={finished / 'best.pt'}", f"metrics_out={out}", "progress=false",
                                   "metrics_out_overwrite=true", f"run_dir={tmp_path / 'e'}"]))
    assert json.loads(out.read_text())["num_queries"] == 8 and out.stat().st_mtime >= start - 1


def test_two_evaluations_with_one_metrics_out_lose_no_result(tmp_path):
    """The existence check runs before an evaluation and the write after it; a second evaluation that wrote the
    same metrics_out in between is not overwritten in silence: this one fails, naming the file, with its numbers."""
    out = tmp_path / "metrics.json"
    run.write_metrics(out, {"R@1": 0.25}, overwrite=False)
    with pytest.raises(ConfigError, match=r"created by someone else while this evaluation ran.*\"R@1\": 0.5"):
        run.write_metrics(out, {"R@1": 0.5}, overwrite=False)
    assert json.loads(out.read_text()) == {"R@1": 0.25}
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]  # no temp file left
    run.write_metrics(out, {"R@1": 0.5}, overwrite=True)
    assert json.loads(out.read_text()) == {"R@1": 0.5}
