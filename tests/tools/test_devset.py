"""tools/devset/assemble.py and its manifest: a tiny git repository stands in for the public sources."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import re
import subprocess

import cv2
import numpy as np
import pytest

from conftest import REPO

spec = importlib.util.spec_from_file_location("devset_assemble", REPO / "tools" / "devset" / "assemble.py")
assemble = importlib.util.module_from_spec(spec)
spec.loader.exec_module(assemble)

SOURCE_REPO = "someone/crossview-demo"


def git(*args, cwd):
    who = ["-c", "user.name=test", "-c", "user.email=test@example.com", "-c", "commit.gpgsign=false"]
    return subprocess.run(["git", *who, *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


@pytest.fixture
def source(tmp_path):
    """A mirror folder holding one committed repository with a panorama and an aerial tile, as the fetch tool
    leaves them (<owner>+<name>/, the git directory inside); returns (mirror, commit, {path: bytes})."""
    work = tmp_path / "mirror" / SOURCE_REPO.replace("/", "+")
    (work / "demo").mkdir(parents=True)
    rng = np.random.default_rng(0)
    files = {"demo/ground.jpg": rng.integers(0, 255, (16, 64, 3), np.uint8),
             "demo/aerial.png": rng.integers(0, 255, (32, 32, 3), np.uint8)}
    data = {}
    for path, image in files.items():
        ok, buf = cv2.imencode(path[-4:], image)
        assert ok
        data[path] = buf.tobytes()
        (work / path).write_bytes(data[path])
    git("init", "-q", cwd=work)
    git("add", ".", cwd=work)
    git("commit", "-q", "-m", "demo pair", cwd=work)
    return tmp_path / "mirror", git("rev-parse", "HEAD", cwd=work), data


def entry(kind, pair, role, path, commit, data, conversion=None, **extra):
    return {"kind": kind, "pair": pair, "role": role, "repository": SOURCE_REPO, "commit": commit, "path": path,
            "sha256": hashlib.sha256(data[path]).hexdigest(), "licence": "none", "original_id": pair,
            "conversion": conversion or {"format": "copy", "crop": None}, "source": "a test pair", **extra}


def write_manifest(path, entries):
    path.write_text(json.dumps({"files": entries}))
    return path


def demo_manifest(tmp_path, commit, data):
    jpeg = {"format": "jpeg", "crop": None}
    return write_manifest(tmp_path / "manifest.json", [
        entry("cvusa_like", "usa-1", "query", "demo/ground.jpg", commit, data),
        entry("cvusa_like", "usa-1", "reference", "demo/aerial.png", commit, data, jpeg),
        entry("cvact_like", "act-1", "query", "demo/ground.jpg", commit, data,
              {"format": "jpeg", "crop": None, "resize": [32, 8]}),
        entry("cvact_like", "act-1", "reference", "demo/aerial.png", commit, data, jpeg),
        entry("other", "other-1", "query", "demo/aerial.png", commit, data, {"format": "jpeg", "crop": [0, 0, 16, 16]}),
        entry("other", "other-1", "reference", "demo/aerial.png", commit, data,
              {"format": "jpeg", "crop": [16, 0, 16, 32]}),
    ])


def test_a_mirrored_repository_assembles_into_folders_geoloc_reads(tmp_path, source):
    import geoloc.datasets  # noqa: F401  (registers the readers)
    from geoloc import registry

    mirror, commit, data = source
    out = tmp_path / "devset"
    manifest = demo_manifest(tmp_path, commit, data)
    assert assemble.main([str(out), "--mirror", str(mirror), "--manifest", str(manifest)]) == 0

    usa = registry.lookup("dataset", "cvusa")(root=str(out / "cvusa_like"), split="val")
    assert usa.num_queries == usa.num_references == 1
    assert usa.queries[0] == out / "cvusa_like" / "streetview" / "panos" / "0000001.jpg"
    assert usa.queries[0].read_bytes() == data["demo/ground.jpg"]  # 'copy' keeps the bytes
    assert cv2.imread(str(usa.references[0])).shape == (32, 32, 3)  # the PNG, written as a JPEG
    with pytest.raises(FileNotFoundError, match="train-19zl.csv"):  # no train split: it is never trained on
        registry.lookup("dataset", "cvusa")(root=str(out / "cvusa_like"), split="train")

    act = registry.lookup("dataset", "cvact")(root=str(out / "cvact_like"), split="val")
    assert act.num_queries == 1 and act.queries[0].name.endswith("_grdView.jpg")
    assert cv2.imread(str(act.queries[0])).shape == (8, 32, 3)  # resized as the manifest says

    other = registry.lookup("dataset", "folder")(root=str(out / "other"), split="all", tile_extent_m=50.0,
                                                 query_view="image")
    assert cv2.imread(str(other.queries[0])).shape == (16, 16, 3)
    assert cv2.imread(str(other.references[0])).shape == (32, 16, 3)

    assert "pair,original_id,repository,commit" in (out / "cvusa_like" / "pairs.csv").read_text()
    text = (out / "README.txt").read_text()
    assert "cvusa_like: N = 1 pairs" in text and "R@1 = 1.0000" in text and "never train" in text
    assert not list(tmp_path.glob(".devset.partial-*"))


def test_chance_level_is_a_random_rankings_recall():
    assert assemble.chance(31, 1) == pytest.approx(1 / 31)
    assert assemble.chance(31, 10) == pytest.approx(10 / 31)
    assert assemble.chance(4, 10) == 1.0


def test_a_sha256_mismatch_is_refused_naming_the_file(tmp_path, source):
    mirror, commit, data = source
    bad = entry("cvusa_like", "usa-1", "reference", "demo/aerial.png", commit, data, {"format": "jpeg", "crop": None})
    bad["sha256"] = "0" * 64
    manifest = write_manifest(tmp_path / "manifest.json",
                              [entry("cvusa_like", "usa-1", "query", "demo/ground.jpg", commit, data), bad])
    with pytest.raises(ValueError, match=r"sha256 mismatch for someone/crossview-demo \w+:demo/aerial.png"):
        assemble.assemble(tmp_path / "devset", assemble.MirrorSource(mirror), manifest)
    assert not (tmp_path / "devset").exists()  # nothing half-written
    assert not list(tmp_path.glob(".devset.partial-*"))


def test_a_repository_missing_from_the_mirror_is_named(tmp_path, source):
    _, commit, data = source
    empty = tmp_path / "empty_mirror"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="repository someone/crossview-demo is not in the mirror"):
        assemble.assemble(tmp_path / "devset", assemble.MirrorSource(empty), demo_manifest(tmp_path, commit, data))


def test_a_destination_inside_the_repository_is_refused(tmp_path):
    with pytest.raises(ValueError, match="inside the repository"):
        assemble.check_destination(REPO / "devset_out")
    with pytest.raises(ValueError, match="inside the repository"):
        assemble.check_destination(REPO)
    assert assemble.main([str(REPO / "devset_out"), "--mirror", str(tmp_path)]) == 1
    assert not (REPO / "devset_out").exists()


def test_an_existing_non_empty_destination_is_refused(tmp_path, source):
    mirror, commit, data = source
    out = tmp_path / "devset"
    out.mkdir()
    (out / "keep.txt").write_text("someone's file")
    with pytest.raises(ValueError, match="non-empty folder; nothing is overwritten"):
        assemble.assemble(out, assemble.MirrorSource(mirror), demo_manifest(tmp_path, commit, data))
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    (out / "keep.txt").unlink()  # an empty folder is taken
    assert assemble.assemble(out, assemble.MirrorSource(mirror), demo_manifest(tmp_path, commit, data)) == {
        "cvusa_like": 1, "cvact_like": 1, "other": 1}


def test_an_incomplete_pair_is_refused(tmp_path, source):
    _, commit, data = source
    manifest = write_manifest(tmp_path / "manifest.json",
                              [entry("cvusa_like", "usa-1", "query", "demo/ground.jpg", commit, data)])
    with pytest.raises(ValueError, match="pair usa-1 has roles \\['query'\\]; it needs exactly one query and one"):
        assemble.load_manifest(manifest)


def test_the_real_manifest_is_well_formed():
    manifest = json.loads((REPO / "tools" / "devset" / "manifest.json").read_text())
    entries = manifest["files"]
    assert entries
    roles = {}
    for e in entries:
        where = f"{e.get('pair')} {e.get('role')}"
        assert re.fullmatch(r"[0-9a-f]{40}", e["commit"]), where
        assert e["path"] and not e["path"].startswith("/"), where
        assert re.fullmatch(r"[0-9a-f]{64}", e["sha256"]), where
        assert isinstance(e["licence"], str) and e["licence"].strip(), where
        assert e["kind"] in assemble.KINDS and e["source"].strip(), where
        assert e["conversion"]["format"] in ("copy", "jpeg"), where
        if e["conversion"]["format"] == "copy":
            assert e["path"].lower().endswith((".jpg", ".jpeg")), f"{where}: only a JPEG is copied as one"
        if e["kind"] == "vigor_like":
            assert "offset_px" in e, f"{where}: a VIGOR-like pair says its offset, or null when the source has none"
        roles.setdefault(e["pair"], []).append(e["role"])
    incomplete = {p: r for p, r in roles.items() if sorted(r) != ["query", "reference"]}
    assert not incomplete, f"pairs without exactly one query and one reference: {incomplete}"
    assert assemble.manifest_problems(entries) == []
    kinds = {e["pair"]: e["kind"] for e in entries}
    assert sum(k != "other" for k in kinds.values()) >= 40  # the target, panoramic kinds alone
