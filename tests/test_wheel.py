"""A wheel trains without its checkout: geoloc is built into a wheel, installed in a fresh venv, and `geoloc train`
(one tiny epoch), `geoloc evaluate` (saving a gallery) and `geoloc localize` run from an empty folder, composing the
configs the wheel ships (geoloc/conf/, package data), and `geoloc serve` and `robustness` compose theirs.

The fresh venv has no pip and none of geoloc's dependencies of its own: a .pth line puts this interpreter's
site-packages on its path, and a .pth line does not run the .pth files it points at, so the editable geoloc of this
environment stays out of it. The test asserts that the geoloc it runs is the wheel's.
"""

from __future__ import annotations

import json
import shutil
import site
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from conftest import REPO, TINY, write_cvusa

pytestmark = pytest.mark.slow


def run(cmd: list[str], cwd: Path, timeout: int = 600) -> subprocess.CompletedProcess:
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{' '.join(map(str, cmd))}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


def built_wheel(tmp: Path) -> Path:
    """The wheel of geoloc's package folder and pyproject.toml alone (copied, so the build leaves no trace in the
    checkout)."""
    source = tmp / "source"
    shutil.copytree(REPO / "geoloc", source / "geoloc", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, source / name)
    # this environment's setuptools where it has one; else pip's isolated build fetches it from the index
    isolation = ["--no-build-isolation"] if _has("setuptools") else []
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", *isolation, "-q", "-w", str(tmp / "dist"), str(source)],
        cwd=tmp)
    (wheel,) = (tmp / "dist").glob("geoloc-*.whl")
    return wheel


def _has(module: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(module) is not None


def fresh_venv(tmp: Path, wheel: Path) -> Path:
    """A venv holding the wheel; the dependencies come from this environment's site-packages. -> its bin/."""
    venv = tmp / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=tmp)
    python = venv / "bin" / "python"
    purelib = Path(run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                       cwd=tmp).stdout.strip())
    ours = {sysconfig.get_paths()["purelib"], *site.getsitepackages()}
    (purelib / "_geoloc_test_dependencies.pth").write_text("\n".join(sorted(ours)) + "\n")
    run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps", "--no-index",
         str(wheel)], cwd=tmp)
    return venv / "bin"


def test_a_wheel_trains_evaluates_and_localizes_from_an_empty_folder(tmp_path):
    wheel = built_wheel(tmp_path)
    bin_dir = fresh_venv(tmp_path, wheel)
    where = run([str(bin_dir / "python"), "-c", "import geoloc; print(geoloc.__file__)"], cwd=tmp_path).stdout
    assert str(tmp_path / "venv") in where and str(REPO) not in where  # the wheel's geoloc, not the checkout's
    # the weights shipped in the package (docs/backbones.md) come with it, and pass their card's checksum
    run([str(bin_dir / "python"), "-c", "from geoloc.models.backbones import vgg16; vgg16(width=0.125, "
         "pretrained=True, weights_path='geoloc:synthetic_vgg16_cpu', batchnorm=True)"], cwd=tmp_path)

    empty = tmp_path / "empty"
    empty.mkdir()
    root = write_cvusa(tmp_path / "cvusa", n_train=12, n_val=8)
    geoloc = str(bin_dir / "geoloc")
    run([geoloc, "train", *TINY, f"dataset.root={root}", "trainer.max_epochs=1", "hydra.run.dir=run"], cwd=empty)
    ckpt = empty / "run" / "best.pt"
    assert ckpt.is_file() and "[epoch 0]" in (empty / "run" / "train.log").read_text()

    run([geoloc, "evaluate", f"ckpt={ckpt}", "device=cpu", "progress=false", "num_workers=0", "gallery.save=gallery",
         "metrics_out=metrics.json", "hydra.run.dir=eval"], cwd=empty)
    metrics = json.loads((empty / "metrics.json").read_text())
    assert metrics["num_queries"] == 8 and 0.0 <= metrics["R@1"] <= 1.0
    assert (empty / "gallery").is_dir()

    image = next((root / "streetview" / "panos").glob("*.jpg"))
    run([geoloc, "localize", f"ckpt={ckpt}", "gallery=gallery", f"image={image}", "topk=3", "device=cpu",
         "out=answers"], cwd=empty)
    answers = [json.loads(line) for line in (empty / "answers" / "localize.jsonl").read_text().splitlines()]
    assert len(answers) == 1 and len(answers[0]["topk"]) == 3

    # the apps that compose their yaml in-process (geoloc/conf/serve.yaml, robustness.yaml) find it in the wheel
    for args, says in ((["serve", "ckpt=absent.pt", "gallery=gallery"], "checkpoint not found: absent.pt"),
                       (["robustness", "ckpt=absent.pt", "fovs=[90]"], "ckpt=absent.pt is not a file")):
        refused = subprocess.run([geoloc, *args], cwd=empty, capture_output=True, text=True, timeout=300,
                                 check=False)
        assert refused.returncode == 2 and says in refused.stderr, refused.stderr
