"""University-1652: the reader on a hand-written folder in the released layout, the tilted drone camera against
a brute-force projection, and the synthetic u1652 layout read back by the reader."""
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from geoloc.datasets.u1652 import u1652_split
from geoloc.synthetic import MARKER, generate
from geoloc.synthetic.classes import BUILDINGS
from geoloc.synthetic.drone import oblique_view
from geoloc.synthetic.light import Lighting, Sun
from geoloc.synthetic.sky import Sky
from geoloc.synthetic.world import World

from conftest import REPO


def _touch(path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")  # the reader never decodes


@pytest.fixture
def released(tmp_path):
    """Train buildings 0002, 0007; test buildings 0003, 0011 with query and gallery views; 0500 gallery only."""
    root = tmp_path / "University-1652"
    for b in ("0002", "0007"):
        _touch(root / f"train/satellite/{b}/{b}.jpg")
        for k in (1, 2, 3):
            _touch(root / f"train/drone/{b}/image-{k:02d}.jpeg")
        _touch(root / f"train/street/{b}/0.jpg")
    for b in ("0003", "0011", "0500"):
        _touch(root / f"test/gallery_satellite/{b}/{b}.jpg")
        for k in (1, 2):
            _touch(root / f"test/gallery_drone/{b}/image-{k:02d}.jpeg")
        if b != "0500":
            _touch(root / f"test/query_satellite/{b}/{b}.jpg")
            for k in (1, 2):
                _touch(root / f"test/query_drone/{b}/image-{k:02d}.jpeg")
    _touch(root / "test/query_drone/0003/notes.txt")  # not an image: skipped
    return root


def test_drone_to_satellite(released):
    test = u1652_split(released, "test", "drone_to_satellite")
    assert test.name == "u1652/drone_to_satellite/test"
    assert [q.relative_to(released).as_posix() for q in test.queries][:2] == [
        "test/query_drone/0003/image-01.jpeg", "test/query_drone/0003/image-02.jpeg"]
    assert test.query_labels.tolist() == [3, 3, 11, 11]
    assert test.reference_labels.tolist() == [3, 11, 500]  # the distractor stays in the gallery
    assert test.positives.tolist() == [0, 0, 1, 1]
    train = u1652_split(released, "train", "drone_to_satellite")
    assert train.num_queries == 6 and train.num_references == 2 and train.positives.tolist() == [0] * 3 + [1] * 3


def test_satellite_to_drone_labels_every_view(released):
    test = u1652_split(released, "test", "satellite_to_drone")
    assert test.query_labels.tolist() == [3, 11] and test.reference_labels.tolist() == [3, 3, 11, 11, 500, 500]
    assert test.positives.tolist() == [0, 2]  # the first drone view of the building
    relevant = [np.flatnonzero(test.reference_labels == lab).tolist() for lab in test.query_labels]
    assert relevant == [[0, 1], [2, 3]]  # AP counts every view of the building
    train = u1652_split(released, "train", "satellite_to_drone")
    assert train.queries[1] == released / "train/satellite/0007/0007.jpg" and train.positives.tolist() == [0, 3]


def test_bad_input(released):
    with pytest.raises(ValueError, match="direction must be one of"):
        u1652_split(released, "test", "street_to_satellite")
    with pytest.raises(ValueError, match="split must be one of"):
        u1652_split(released, "val")
    with pytest.raises(FileNotFoundError, match="query_drone not found"):
        u1652_split(released.parent, "test")
    _touch(released / "test/query_drone/0042/image-01.jpeg")
    with pytest.raises(ValueError, match=r"1 query building\(s\) of .*query_drone have no image in "
                                         r".*gallery_satellite, e.g. building 0042"):
        u1652_split(released, "test")
    _touch(released / "train/drone/misc/image-01.jpeg")
    with pytest.raises(ValueError, match="misc is not a building id"):
        u1652_split(released, "train")


def test_tilted_camera_against_a_projection():
    """A thin tower seen by the pitched pinhole lands on the pixel a plain pinhole projection gives."""
    world = World.empty(160.0, 0.5, (120, 120, 120))
    tower = np.array([12.0, 20.0])
    world.stamp_box(*tower, 1.5, 1.5, 0.0, 30.0, 0.0, BUILDINGS, (200, 0, 0), (200, 0, 0))
    sun = Sun(120.0, 50.0)
    cam, yaw, pitch, size, fov = np.array([-10.0, -35.0, 40.0]), 20.0, 35.0, 96, 60.0
    _, cls = oblique_view(world, Lighting(world, sun), Sky(np.random.default_rng(0), sun), tuple(cam), yaw, pitch,
                          size, fov, 0.0)
    # brute force: the camera basis in (east, north, up) and the pinhole equations
    a, p = np.deg2rad(yaw), np.deg2rad(pitch)
    forward = np.array([np.sin(a) * np.cos(p), np.cos(a) * np.cos(p), -np.sin(p)])
    right = np.array([np.cos(a), -np.sin(a), 0.0])
    up = np.cross(right, forward)
    f = (size / 2) / np.tan(np.deg2rad(fov) / 2)
    for z in (5.0, 15.0, 25.0):
        d = np.array([*tower, z]) - cam
        u = f * d @ right / (d @ forward) + size / 2
        v = -f * d @ up / (d @ forward) + size / 2
        assert cls[int(v), int(u)] == BUILDINGS, (z, u, v)
        assert cls[int(v), int(u) + 4] != BUILDINGS and cls[int(v), int(u) - 4] != BUILDINGS  # a thin tower


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    return generate("u1652", tmp_path_factory.mktemp("u1652") / "ds", seed=1, preset="u1652_tiny", progress=False)


def test_synthetic_layout_reads_back(synthetic):
    marker = json.loads((synthetic / MARKER).read_text())
    assert marker["complete"] and marker["options"] == {"drone_views": 3, "extra_gallery": 1}
    train = u1652_split(synthetic, "train", "drone_to_satellite")
    assert train.num_queries == 3 * 3 and train.num_references == 3
    assert train.query_labels.tolist() == [1, 1, 1, 2, 2, 2, 3, 3, 3]
    test = u1652_split(synthetic, "test", "drone_to_satellite")
    assert test.query_labels.tolist() == [4, 4, 4, 5, 5, 5] and test.reference_labels.tolist() == [4, 5, 6]
    back = u1652_split(synthetic, "test", "satellite_to_drone")
    assert back.num_queries == 2 and back.num_references == 9 and back.positives.tolist() == [0, 3]
    for b in ("0004", "0005"):  # as in the release, query and gallery hold the same files
        for view in ("satellite", "drone"):
            q = sorted((synthetic / f"test/query_{view}/{b}").iterdir())
            g = sorted((synthetic / f"test/gallery_{view}/{b}").iterdir())
            assert [x.read_bytes() for x in q] == [x.read_bytes() for x in g]
    assert cv2.imread(str(train.queries[0])).shape == (48, 48, 3)
    assert cv2.imread(str(train.references[0])).shape == (64, 64, 3)
    views = [cv2.imread(str(q)).astype(float) for q in train.queries[:3]]
    assert np.abs(views[0] - views[1]).mean() > 5  # the orbit moves: the views differ


def test_cli_and_geometry_check(tmp_path):
    out = tmp_path / "cli"
    cmd = [sys.executable, str(REPO / "data_prep/synthetic.py"), "--layout", "u1652", "--out", str(out), "--train",
           "1", "--val", "0", "--preset", "u1652_tiny", "--drone-views", "2", "--extra-gallery", "0", "--no-progress"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert json.loads((out / MARKER).read_text())["options"] == {"drone_views": 2, "extra_gallery": 0}
    assert len(list((out / "train/drone/0001").iterdir())) == 2
    with pytest.raises(ValueError, match="world_margin >= 1.2"):
        generate("u1652", tmp_path / "x", 1, 0, preset="u1652_tiny", world_margin=1.0, progress=False)
    assert not (tmp_path / "x").exists()


def test_view_from_inside_a_building_renders():
    """A camera inside a tower sees only walls (no ground texture to sample): it renders, all building."""
    world = World.empty(64.0, 0.5, (120, 120, 120))
    world.stamp_box(0.0, 0.0, 10.0, 10.0, 0.0, 30.0, 0.0, BUILDINGS, (90, 90, 90), (150, 140, 130))
    sun = Sun(120.0, 50.0)
    rgb, cls = oblique_view(world, Lighting(world, sun), Sky(np.random.default_rng(0), sun), (0.0, 0.0, 12.0),
                            0.0, 30.0, 16, 60.0, 0.0)
    assert rgb.shape == (16, 16, 3) and (cls == BUILDINGS).all()
