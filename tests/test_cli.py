"""The one `geoloc` command reaches every app, with the same arguments and exit status as the .py entry points."""

from __future__ import annotations

import subprocess
import sys

import pytest
from conftest import REPO

from geoloc import cli


def geoloc(*args, cwd):
    return subprocess.run([sys.executable, "-m", "geoloc.cli", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


def test_help_lists_every_app():
    text = cli.usage()
    for name in ("train", "evaluate", "localize", "export", "serve"):
        assert f"\n  {name} " in text


@pytest.mark.slow
def test_a_subcommand_is_its_entry_point(tmp_path):
    """`geoloc train --cfg job` prints the composed config as `python train.py --cfg job` does; a failing
    evaluate exits non-zero and names the file, as evaluate.py does."""
    via_cli = geoloc("train", "--cfg", "job", "seed=3", cwd=tmp_path)
    direct = subprocess.run([sys.executable, str(REPO / "train.py"), "--cfg", "job", "seed=3"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=300)
    assert via_cli.returncode == direct.returncode == 0
    assert via_cli.stdout == direct.stdout and "seed: 3" in via_cli.stdout
    failed = geoloc("evaluate", f"ckpt={tmp_path / 'absent.pt'}", cwd=tmp_path)
    assert failed.returncode != 0 and "absent.pt" in failed.stderr + failed.stdout


def test_an_unknown_subcommand_is_refused_with_the_list():
    assert cli.main(["trian"]) == 2


def test_list_prints_every_kind_with_its_names_and_keys(capsys):
    from geoloc import registry

    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    for kind in registry.kinds():  # every declared kind, and each of its names
        assert f"\n{kind}  (" in f"\n{out}"
        for name in registry.names(kind):
            assert f"  {name} " in out, (kind, name)
    assert "gms_triplet       geoloc.losses.gms_triplet_loss.GMSTripletLoss\n" in out
    assert "alpha=10.0  queue_size=1024  queue_start_epoch=0" in out  # the factory's keys and defaults
    assert "(loss.name=NAME; geoloc passes dim)" in out  # run-time arguments are not config keys


def test_list_refuses_a_kind_that_does_not_exist(capsys):
    assert cli.main(["list", "losses"]) == 2
    assert "unknown kind(s) ['losses']" in capsys.readouterr().err
