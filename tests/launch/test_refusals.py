"""A refusal (ConfigError, RunDirTaken, a missing file) ends an entry point with one clear line and no traceback,
leaving no folder; HYDRA_FULL_ERROR=1 still shows the traceback."""

from __future__ import annotations

import os
import subprocess
import sys

from conftest import REPO

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
BAD = ["ckpt=x", "gallery=y", "image=z", "fov=abc"]  # refused before anything is loaded


def localize_py(cwd, env):
    return subprocess.run([sys.executable, str(REPO / "localize.py"), *BAD], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def test_a_refusal_is_one_line_and_leaves_no_folder(tmp_path):
    env = {key: value for key, value in ENV.items() if key != "HYDRA_FULL_ERROR"}
    proc = localize_py(tmp_path, env)
    assert proc.returncode == 1
    assert proc.stderr.splitlines() == ["ConfigError: localize.py: fov='abc' is not a number (the horizontal field "
                                        "of view in degrees, in (0, 360]: 360 for a full panorama (the default))"]
    assert not [p for p in (tmp_path / "outputs").rglob("*") if p.is_file() or p.name.startswith("20")]


def test_hydra_full_error_shows_the_traceback(tmp_path):
    proc = localize_py(tmp_path, {**ENV, "HYDRA_FULL_ERROR": "1"})
    assert proc.returncode == 1
    assert "Traceback" in proc.stderr and "ConfigError: localize.py: fov='abc'" in proc.stderr


def test_the_geoloc_command_prints_the_line_too(tmp_path):
    env = {key: value for key, value in ENV.items() if key != "HYDRA_FULL_ERROR"}
    proc = subprocess.run([sys.executable, "-m", "geoloc.cli", "localize", *BAD], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)  # a process: Hydra configures its logging
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert "ConfigError: localize.py: fov='abc'" in proc.stderr
    assert not [p for p in (tmp_path / "outputs").rglob("*") if p.is_file() or p.name.startswith("20")]
