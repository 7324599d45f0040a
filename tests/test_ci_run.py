""".ci/run with stand-in `pip` and `pytest`: versions before the tests, every failure exit is a failure."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

from conftest import REPO

README_COMMAND = 'pip install -e ".[dev]" && pytest'


def _ci(tmp_path, pip_rc: int, pytest_rc: int) -> subprocess.CompletedProcess:
    """Run a copy of .ci/run whose `pip` and `pytest` are stubs that print their name and exit with the code given."""
    repo = tmp_path / "clone"
    (repo / ".ci").mkdir(parents=True)
    shutil.copy(REPO / ".ci" / "run", repo / ".ci" / "run")
    stubs = tmp_path / "bin"
    stubs.mkdir()
    for name, rc in (("pip", pip_rc), ("pytest", pytest_rc)):
        (stubs / name).write_text(f'#!/bin/sh\necho "STUB {name} $*"\nexit {rc}\n')
        (stubs / name).chmod(0o755)
    path = os.pathsep.join([str(stubs), os.path.dirname(sys.executable), os.environ["PATH"]])  # stubs, then this venv
    env = {**os.environ, "PATH": path, "PYTHONPATH": str(REPO)}
    return subprocess.run(["bash", str(repo / ".ci" / "run")], env=env, capture_output=True, text=True, timeout=120)


def test_the_readme_test_command_is_run_verbatim():
    assert README_COMMAND in (REPO / "README.md").read_text()
    assert README_COMMAND in (REPO / ".ci" / "run").read_text()
    assert "set -euo pipefail" in (REPO / ".ci" / "run").read_text()


def test_versions_are_printed_after_the_install_and_before_the_tests(tmp_path):
    proc = _ci(tmp_path, pip_rc=0, pytest_rc=0)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    order = [next(i for i, line in enumerate(lines) if line.startswith(p)) for p in
             ('STUB pip install -e .[dev]', "environment: ", "STUB pytest")]
    assert order == sorted(order), lines
    env_line = lines[order[1]]
    for name in ("python", "torch", "torchvision", "numpy", "opencv", "faiss", "scipy", "hydra-core", "threads"):
        assert f"| {name} " in env_line or env_line.startswith(f"environment: {name} "), name


@pytest.mark.parametrize("pip_rc,pytest_rc", [(0, 1), (0, 5), (1, 0)])
def test_a_failed_install_failing_tests_or_no_tests_collected_fail_ci(tmp_path, pip_rc, pytest_rc):
    proc = _ci(tmp_path, pip_rc=pip_rc, pytest_rc=pytest_rc)
    assert proc.returncode == (pip_rc or pytest_rc), proc.stdout + proc.stderr
    if pip_rc:
        assert "STUB pytest" not in proc.stdout  # no tests on a broken install
    if pytest_rc == 5:
        assert "collected no tests" in proc.stderr
