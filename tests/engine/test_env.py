"""The recorded environment: versions read independently, the live thread count, and where a run keeps it."""

from __future__ import annotations

import json
import platform

import cv2
import numpy as np
import pytest
import scipy
import torch
import torchvision
from geoloc.engine import Trainer, TrainerConfig
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine import env as env_mod

from toy_task import Points, ScriptedRecall


def test_versions_match_what_the_modules_report():
    env = env_mod.environment()
    assert env["python"] == platform.python_version()
    assert env["torch"] == torch.__version__
    assert env["torchvision"] == torchvision.__version__.split("+")[0]  # the wheel metadata has no build tag
    assert env["numpy"] == np.__version__
    assert env["scipy"] == scipy.__version__
    assert env["opencv"].startswith(cv2.__version__)  # the wheel adds a build number: 4.10.0.84 for cv2 4.10.0
    assert env["cuda"] == torch.version.cuda


def test_threads_are_read_when_asked_not_at_import(monkeypatch):
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        monkeypatch.setenv("OMP_NUM_THREADS", "1")
        env = env_mod.environment()
        assert (env["threads"], env["OMP_NUM_THREADS"]) == (1, "1")
    finally:
        torch.set_num_threads(before)


def test_an_absent_package_is_none_and_shown_as_a_dash(monkeypatch):
    monkeypatch.setattr(env_mod, "PACKAGES", {"torch": ("torch",), "nope": ("no-such-distribution-xyz",)})
    env = env_mod.environment()
    assert env["nope"] is None
    line = env_mod.describe(env)
    assert f"torch {torch.__version__}" in line and "nope -" in line


def test_fit_prints_the_environment_and_keeps_it_in_env_json_and_the_checkpoint(tmp_path, capsys):
    cfg = TrainerConfig(max_epochs=1, num_workers=0, device="cpu", progress=False, persistent_workers=False)
    Trainer(cfg, tmp_path).fit(ScriptedRecall(), Points(), None, batch_size=2)
    saved = json.loads((tmp_path / "env.json").read_text())
    assert saved == env_mod.environment()
    assert ckpt_io.load(tmp_path / "last.pt")["environment"] == saved
    printed = [line for line in capsys.readouterr().out.splitlines() if line.startswith("environment:")]
    assert printed == [env_mod.describe(saved)]
    assert f"threads {torch.get_num_threads()}" in printed[0]


@pytest.mark.parametrize("key", list(env_mod.PACKAGES))
def test_every_listed_package_is_installed_here(key):
    # the dev extra installs all of them; a None here means a distribution name in PACKAGES is wrong
    assert env_mod.environment()[key] is not None
