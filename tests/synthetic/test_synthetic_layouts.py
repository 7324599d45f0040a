"""Synthetic datasets: files and split/index files as the real loaders read them, determinism, refusal, resume."""
import csv
import filecmp
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
from geoloc.synthetic import MARKER, DatasetMismatchError, generate

from conftest import REPO as ROOT

from geoloc.tasks.mmdip.readers import load_class_fractions


def _tree(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def cvusa(tmp_path_factory):
    return generate("cvusa", tmp_path_factory.mktemp("cvusa") / "ds", 5, 3, seed=7, preset="tiny", progress=False)


def test_cvusa_layout_and_splits(cvusa):
    train = (cvusa / "splits/train-19zl.csv").read_bytes().decode()
    val = (cvusa / "splits/val-19zl.csv").read_bytes().decode()
    assert train.startswith("bingmap/19/0000001.jpg,streetview/panos/0000001.jpg,streetview/annotations/0000001.png\n")
    rows = list(csv.reader(train.splitlines())) + list(csv.reader(val.splitlines()))
    assert len(rows) == 8 and all(len(r) == 3 for r in rows)
    assert rows[5][0] == "bingmap/19/0000006.jpg"  # val numbering follows train
    for aerial, pano, ann in rows:
        a = cv2.imread(str(cvusa / aerial))
        p = cv2.imread(str(cvusa / pano))
        lab = cv2.imread(str(cvusa / ann), cv2.IMREAD_UNCHANGED)
        assert a.shape == (64, 64, 3) and p.shape == (32, 176, 3)
        assert lab.shape == (32, 176) and lab.dtype == np.uint8 and lab.max() <= 9
    marker = json.loads((cvusa / MARKER).read_text())
    assert marker["complete"] and marker["layout"] == "cvusa" and marker["seed"] == 7


def test_cvact_mat_reads_like_the_real_one(tmp_path):
    root = generate("cvact", tmp_path / "act", 4, 2, seed=1, preset="tiny", progress=False)
    mat = scipy.io.loadmat(str(root / "ACT_data.mat"))
    ids = mat["panoIds"]
    train = mat["trainSet"]["trainInd"][0][0] - 1  # 1-based, MATLAB style
    val = mat["valSet"]["valInd"][0][0] - 1
    assert len(ids) == 6 and mat["utm"].shape == (6, 2)
    assert train.shape == (4, 1) and val.shape == (2, 1)
    assert sorted(train[:, 0].tolist() + val[:, 0].tolist()) == list(range(6))
    assert np.array_equal(mat["valSetAll"]["valInd"][0][0] - 1, val)
    for k in range(len(val)):
        i = ids[val[k][0]]  # the SAFA / Sample4Geo access pattern
        g = cv2.imread(str(root / "ANU_data_small/streetview" / (i + "_grdView.jpg")))
        s = cv2.imread(str(root / "ANU_data_small/satview_polish" / (i + "_satView_polish.jpg")))
        assert g.shape == (64, 128, 3) and s.shape == (64, 64, 3)


def test_dynamic_layout(tmp_path):
    root = generate("dynamic", tmp_path / "dyn", 2, 1, seed=2, preset="dynamic_tiny", progress=False)
    lines = (root / "splits/train.csv").read_text().splitlines()
    assert lines[0] == "sample,place,role,x,y,yaw,sun_azimuth,sun_elevation"
    rows = list(csv.DictReader((root / "splits/train.csv").read_text().splitlines()))
    val = list(csv.DictReader((root / "splits/val.csv").read_text().splitlines()))
    assert [r["role"] for r in rows] == ["reference", "query"] * 2 and len(val) == 2
    assert {r["place"] for r in val}.isdisjoint({r["place"] for r in rows})
    for r in rows + val:
        s = r["sample"]
        for d in ("rgb_dynamic", "rgb_static"):
            assert cv2.imread(str(root / d / f"{s}.png")).shape == (48, 48, 3)
        st = cv2.imread(str(root / "label_static" / f"{s}.png"), cv2.IMREAD_UNCHANGED)
        dy = cv2.imread(str(root / "label_dynamic" / f"{s}.png"), cv2.IMREAD_UNCHANGED)
        mask = cv2.imread(str(root / "mask_dynamic" / f"{s}.png"), cv2.IMREAD_UNCHANGED)
        assert st.max() <= 7 and dy.max() <= 9 and set(np.unique(mask)) <= {0, 255}
        assert np.array_equal(mask == 255, dy >= 8)
    # the renderer writes no task's files: MMDIP's reader counts the class fractions on first use, and keeps them
    assert not (root / "class_fractions.json").exists()
    fractions = load_class_fractions(root)
    frac = json.loads((root / "class_fractions.json").read_text())
    assert len(frac["classes"]) == 8 and frac["fractions"] == fractions and abs(sum(fractions) - 1) < 1e-4


def test_deterministic_across_workers(tmp_path, cvusa):
    again = generate("cvusa", tmp_path / "w2", 5, 3, seed=7, preset="tiny", workers=2, progress=False)
    assert _tree(cvusa) == _tree(again)
    other = generate("cvusa", tmp_path / "s8", 5, 3, seed=8, preset="tiny", progress=False)
    assert not filecmp.cmp(cvusa / "bingmap/19/0000001.jpg", other / "bingmap/19/0000001.jpg", shallow=False)


def test_reuse_refuse_and_resume(tmp_path, cvusa):
    before = _tree(cvusa)
    assert generate("cvusa", cvusa, 5, 3, seed=7, preset="tiny", progress=False) == cvusa  # same args: no work
    with pytest.raises(DatasetMismatchError, match="seed"):
        generate("cvusa", cvusa, 5, 3, seed=9, preset="tiny", progress=False)
    with pytest.raises(DatasetMismatchError, match="config.aerial_size"):
        generate("cvusa", cvusa, 5, 3, seed=7, preset="tiny", aerial_size=96, progress=False)
    assert _tree(cvusa) == before  # nothing touched
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not a geoloc synthetic dataset"):
        generate("cvusa", foreign, 2, 1, preset="tiny", progress=False)
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]

    # An interrupted run: marker says incomplete, some samples and the splits are missing -> resumed, identical.
    part = tmp_path / "part"
    generate("cvusa", part, 5, 3, seed=7, preset="tiny", progress=False)
    marker = json.loads((part / MARKER).read_text())
    (part / MARKER).write_text(json.dumps({**marker, "complete": False}))
    (part / ".geoloc_partial").mkdir()
    for n in range(1, 6):
        (part / ".geoloc_partial" / f"{n:07d}.json").write_text('{"split": "train", "rows": []}')
    for p in ("bingmap/19/0000007.jpg", "splits/val-19zl.csv"):
        (part / p).unlink()
    generate("cvusa", part, 5, 3, seed=7, preset="tiny", progress=False)
    assert _tree(part) == before


@pytest.mark.parametrize(
    "kwargs, err, match",
    [
        (dict(layout="kitti"), ValueError, "unknown layout"),
        (dict(preset="huge"), ValueError, "unknown preset"),
        (dict(train=-1), ValueError, "train must be"),
        (dict(train=0, val=0), ValueError, "at least 1"),
        (dict(workers=0), ValueError, "workers"),
        (dict(aerial_size=4), ValueError, "aerial_size"),
        (dict(style="lunar"), ValueError, "style"),
        (dict(gap_strength=2.0), ValueError, "strength"),
        (dict(jpeg_quality=0), ValueError, "jpeg_quality"),
        (dict(colour="red"), TypeError, "unknown synthetic option"),
    ],
)
def test_bad_arguments(tmp_path, kwargs, err, match):
    args = dict(layout="cvusa", out=tmp_path / "x", train=2, val=1, preset="tiny", progress=False)
    args.update(kwargs)
    with pytest.raises(err, match=match):
        generate(**args)
    assert not (tmp_path / "x").exists()


def test_cli(tmp_path):
    out = tmp_path / "cli"
    cmd = [sys.executable, str(ROOT / "data_prep/synthetic.py"), "--layout", "cvusa", "--out", str(out),
           "--train", "2", "--val", "1", "--seed", "3", "--preset", "tiny", "--no-progress", "--gap-strength", "0.2"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert json.loads((out / MARKER).read_text())["config"]["gap_strength"] == 0.2
    bad = subprocess.run(cmd[:-2] + ["--seed", "4"], capture_output=True, text=True, cwd=tmp_path)
    assert bad.returncode == 2 and "other arguments" in bad.stderr
