"""A saved gallery's folder: bound to the weights and the split that built it, written whole or not at all, never
replaced unless asked, and every file checked on load with the file named (geoloc/gallery/folder.py).
The gallery path runs on given descriptors: no network, no images."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch
from geoloc.config import ConfigError
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval import recall_at_k
from geoloc.gallery import folder as gallery_folder
from geoloc.tasks.crossview import open_gallery

from helpers.calibrated import KNOWN
from helpers.gallery_runs import META, gallery_evaluate, pairs_split


def unit_pairs(n=30, d=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    reference = torch.nn.functional.normalize(torch.randn(n, d, generator=g), dim=1)
    query = torch.nn.functional.normalize(reference + 0.5 * torch.randn(n, d, generator=g), dim=1)
    return query, reference


def build(monkeypatch, folder, split=None, meta=META, **cfg):
    query, reference = unit_pairs()
    split = split or pairs_split(len(query), folder.parent / "data")
    return gallery_evaluate(monkeypatch, split, query, reference, meta=meta, save=str(folder), **cfg)


def load(monkeypatch, folder, split=None, meta=META):
    query, _ = unit_pairs()
    split = split or pairs_split(len(query), folder.parent / "data")
    return gallery_evaluate(monkeypatch, split, query, None, meta=meta, load=str(folder))


def files_of(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


# ---- bound to what built it ------------------------------------------------------------------------------------
def test_a_gallery_of_other_weights_is_refused(monkeypatch, tmp_path):
    folder = tmp_path / "g"
    build(monkeypatch, folder)
    assert load(monkeypatch, folder)["R@1"] == recall_at_k(*unit_pairs())["R@1"]
    other = {**META, "ckpt": "/runs/b/best.pt", "model_fingerprint": "b" * 64}
    with pytest.raises(ConfigError, match=rf"gallery in {folder} was built with other weights \(/runs/a/best.pt\) "
                                          r"than /runs/b/best.pt.*gallery.save=.*gallery.overwrite=true"):
        load(monkeypatch, folder, meta=other)


def test_a_gallery_of_another_split_is_refused_naming_what_differs(monkeypatch, tmp_path):
    """Gallery row j must be the scored split's reference j: a reordered split of the same size, another root,
    another split or another size are each refused by name (they used to give a wrong recall and exit 0)."""
    folder, n = tmp_path / "g", 30
    split = pairs_split(n, tmp_path / "data")
    build(monkeypatch, folder, split)
    reordered = RetrievalSplit("pairs", tmp_path / "data", split.queries[::-1], split.references[::-1], np.arange(n))
    with pytest.raises(ConfigError, match=rf"gallery in {folder} was built from another split.*the reference list: "
                                          r"the same number of references, in another order.*gallery.save="):
        load(monkeypatch, folder, reordered)
    with pytest.raises(ConfigError, match=r"root '.*data' \(gallery\) vs '.*elsewhere' \(this evaluation\)"):
        load(monkeypatch, folder, pairs_split(n, tmp_path / "elsewhere"))
    with pytest.raises(ConfigError, match=r"split 'pairs' \(gallery\) vs 'pairs/test' \(this evaluation\)"):
        load(monkeypatch, folder, pairs_split(n, tmp_path / "data", name="pairs/test"))
    with pytest.raises(ConfigError, match=r"dataset 'pairs' \(gallery\) vs 'vigor'"):
        load(monkeypatch, folder, meta={**META, "dataset": "vigor"})
    query, _ = unit_pairs(n=20)
    with pytest.raises(ConfigError, match=r"num_references 30 \(gallery\) vs 20"):
        gallery_evaluate(monkeypatch, pairs_split(20, tmp_path / "data"), query, None, meta=META, load=str(folder))


def test_a_relative_dataset_root_is_stored_absolute(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    build(monkeypatch, tmp_path / "g", pairs_split(30, "data"))
    info = json.loads((tmp_path / "g" / "gallery.json").read_text())
    assert info["root"] == str((tmp_path / "data").resolve())
    monkeypatch.chdir(tmp_path / "g")  # another folder: the same split, given by its absolute root, still matches
    assert load(monkeypatch, tmp_path / "g", pairs_split(30, tmp_path / "data"))["num_references"] == 30


# ---- saved whole, replaced only when asked ---------------------------------------------------------------------
def test_an_existing_gallery_is_refused_unless_overwrite(monkeypatch, tmp_path):
    folder = tmp_path / "g"
    (folder).mkdir()
    build(monkeypatch, folder)  # an empty folder is free
    before = files_of(folder)
    with pytest.raises(ConfigError, match=rf"gallery.save={folder} already holds a gallery \(built by /runs/a/best.pt "
                                          r"from pairs of .*\): add gallery.overwrite=true"):
        build(monkeypatch, folder, meta={**META, "model_fingerprint": "b" * 64})
    assert files_of(folder) == before
    build(monkeypatch, folder, meta={**META, "model_fingerprint": "b" * 64}, overwrite=True)
    assert json.loads((folder / "gallery.json").read_text())["model_fingerprint"] == "b" * 64
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g"]  # no temporary or old folder left beside it

    other = tmp_path / "notes"
    other.mkdir()
    (other / "todo.txt").write_text("mine")
    with pytest.raises(ConfigError, match="holds files that are not a gallery \\(todo.txt\\)"):
        build(monkeypatch, other, overwrite=True)
    assert (other / "todo.txt").read_text() == "mine"


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "two_renames"])
def test_an_interrupted_save_leaves_the_old_gallery_whole(monkeypatch, tmp_path, exchange):
    """The old write order (descriptors, places, gallery.json) left new descriptors under the old gallery.json when
    interrupted; now every file goes to a temporary folder that is renamed into place at the end."""
    if not exchange:
        monkeypatch.setattr(gallery_folder, "_exchange", lambda a, b: False)
    folder = tmp_path / "g"
    build(monkeypatch, folder)
    before = files_of(folder)
    real = gallery_folder.write_places

    def interrupted(tmp, split, rows=None):
        real(tmp, split, rows)
        raise KeyboardInterrupt("killed after the places were written")

    monkeypatch.setattr(gallery_folder, "write_places", interrupted)
    with pytest.raises(KeyboardInterrupt):
        build(monkeypatch, folder, meta={**META, "model_fingerprint": "b" * 64}, overwrite=True)
    assert files_of(folder) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g"]
    with pytest.raises(KeyboardInterrupt):  # a first save, interrupted, leaves nothing
        build(monkeypatch, tmp_path / "new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g"]
    monkeypatch.setattr(gallery_folder, "write_places", real)
    build(monkeypatch, folder, meta={**META, "model_fingerprint": "b" * 64}, overwrite=True)
    assert json.loads((folder / "gallery.json").read_text())["model_fingerprint"] == "b" * 64
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g"]


def test_a_saved_gallery_gets_the_umask_mode(monkeypatch, tmp_path):
    old = os.umask(0o022)
    try:
        build(monkeypatch, tmp_path / "g")
    finally:
        os.umask(old)
    assert (tmp_path / "g").stat().st_mode & 0o777 == 0o755  # not mkdtemp's 0700: a service user can read it


# ---- every file checked on load --------------------------------------------------------------------------------
def cut(path, keep=0.5):
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def drop_line(path, keep):
    lines = path.read_text().splitlines()
    path.write_text("\n".join(keep(lines)) + "\n")


def write_calibration(folder, record):
    (folder / "calibration.json").write_text(json.dumps(record))


DAMAGE = {  # what is done to a good gallery -> (the file named, what the message says)
    "gallery.pt truncated": (lambda g: cut(g / "gallery.pt"), "gallery.pt", "truncated, corrupt"),
    "gallery.pt of another gallery": (
        lambda g: (g / "gallery.pt").write_bytes((g.parent / "small" / "gallery.pt").read_bytes()),
        "gallery.pt", "holds 20 references of dim 16, but .*gallery.json records 30"),
    "gallery.json empty": (lambda g: (g / "gallery.json").write_text(""), "gallery.json", "is empty"),
    "gallery.json cut": (lambda g: cut(g / "gallery.json"), "gallery.json", "not complete JSON"),
    "gallery.json a list": (lambda g: (g / "gallery.json").write_text("[]"), "gallery.json", "JSON list"),
    "references.jsonl cut line": (lambda g: cut(g / "references.jsonl", 0.7), "references.jsonl",
                                  r"line \d+ is not JSON"),
    "references.jsonl shorter": (lambda g: drop_line(g / "references.jsonl", lambda x: x[:-3]), "references.jsonl",
                                 "holds 27 references, but the gallery has 30 rows"),
    "references.jsonl longer": (lambda g: drop_line(g / "references.jsonl", lambda x: x + x[:2]), "references.jsonl",
                                "holds 32 references, but the gallery has 30 rows"),
    "references.jsonl no path": (lambda g: drop_line(g / "references.jsonl", lambda x: ['{"p": 1}'] + x[1:]),
                                 "references.jsonl", 'line 1: no "path"'),
    "queries.jsonl cut line": (lambda g: cut(g / "queries.jsonl", 0.5), "queries.jsonl", "is not JSON"),
    # a calibration.json that loaded and then failed every request with a heading (500), or failed the service's
    # start with a raw AttributeError naming no file
    "calibration.json targets a list": (lambda g: write_calibration(g, {"calibrated": False, "targets": [1, 2]}),
                                        "calibration.json", r'holds "targets" as a JSON list'),
    "calibration.json feature count": (
        lambda g: write_calibration(g, {"calibrated": True, "targets": {"top1": {**KNOWN.to_json(), "features": [
            "top1_score"], "mean": [0.0], "scale": [1.0], "weights": [4.0]}}}),
        "calibration.json", r"fitted as 'top1' on the features \['top1_score'\], where geoloc computes "
                            r"\['top1_score', 'top1_margin'\]"),
    "calibration.json refiner feature count": (
        lambda g: write_calibration(g, {"calibrated": False, "targets": {"within_5m": {**KNOWN.to_json(),
                                                                                       "target": "within_5m"}}}),
        "calibration.json", r"where geoloc computes \['mass_5m_logit'\]"),
    "calibration.json target not a record": (
        lambda g: write_calibration(g, {"calibrated": True, "targets": {"top1": [1, 2]}}),
        "calibration.json", r"holds a target 'top1' that is not a calibrator record"),
    "calibration.json unknown target": (
        lambda g: write_calibration(g, {"calibrated": True, "targets": {"top1": KNOWN.to_json(), "top5": {}}}),
        "calibration.json", r"holds a target 'top5', which geoloc does not compute \(top1, within_5m\)"),
    "queries.jsonl row out of range": (
        lambda g: drop_line(g / "queries.jsonl", lambda x: x[:-1] + [x[-1].replace('"positive": 29', '"positive": 30')]),
        "queries.jsonl", r'line 30: "positive" must be a gallery row in 0..29, got 30'),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_every_file_of_a_gallery_is_checked_on_load_and_named(monkeypatch, tmp_path, damage):
    do, name, says = DAMAGE[damage]
    folder = tmp_path / "g"
    build(monkeypatch, folder)
    query, reference = unit_pairs(n=20)
    gallery_evaluate(monkeypatch, pairs_split(20, tmp_path / "data"), query, reference, save=str(tmp_path / "small"))
    do(folder)
    with pytest.raises(ConfigError, match=rf"{folder / name}.*{says}.*gallery.save={folder} gallery.overwrite=true"):
        load(monkeypatch, folder)
    with pytest.raises(ConfigError, match=rf"{folder / name}.*{says}"):  # localize.py and the service open it so
        open_gallery(folder, META["model_fingerprint"], META["ckpt"])


def test_a_missing_file_is_named_with_the_way_to_build_it(monkeypatch, tmp_path):
    folder = tmp_path / "g"
    with pytest.raises(FileNotFoundError, match=rf"{folder} holds no saved gallery \(gallery.json\).*gallery.save="):
        open_gallery(folder, META["model_fingerprint"], META["ckpt"])
    build(monkeypatch, folder)
    (folder / "gallery.pt").unlink()
    with pytest.raises(FileNotFoundError, match=rf"gallery in {folder} lacks gallery.pt.*gallery.save="):
        open_gallery(folder, META["model_fingerprint"], META["ckpt"])


# ---- a kind that cannot train on so few references -------------------------------------------------------------
@pytest.mark.parametrize("kind, needed", [("ivfpq", 256), ("pq_refine", 16), ("ivfpq_refine", 16)])
def test_a_trained_kind_on_a_tiny_gallery_says_how_many_references_it_needs(monkeypatch, tmp_path, kind, needed):
    pytest.importorskip("faiss")
    query, reference = unit_pairs(n=12)
    with pytest.raises(ConfigError, match=rf"gallery.kind={kind} builds {kind}, which trains .* needs at least "
                                          rf"{needed} references; this split has 12. Use gallery.kind=flat"):
        gallery_evaluate(monkeypatch, pairs_split(12, tmp_path), query, reference, save=str(tmp_path / "g"),
                         backend="faiss", kind=kind, m=8)
    assert not (tmp_path / "g").exists()
