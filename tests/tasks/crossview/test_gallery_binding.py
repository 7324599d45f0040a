"""evaluate.py gallery.save= / gallery.load= end to end: a gallery answers only the checkpoint and the split that
built it, an existing gallery is kept unless gallery.overwrite=true, and a kind that cannot train on the split is
refused before anything is encoded."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from geoloc.config import ConfigError
from geoloc.launch import run

from conftest import compose_evaluate

pytestmark = pytest.mark.slow  # each module trains a run end to end


def evaluate(tmp_path, ckpt, root, *extra):
    return run.evaluate(compose_evaluate([f"ckpt={ckpt}", "progress=false", "device=cpu", f"dataset.root={root}",
                                          f"run_dir={tmp_path / 'eval'}", *extra]))


@pytest.fixture(scope="module")
def built(finished_run, tmp_path_factory):
    """(dataset root, checkpoint, its gallery of the val split)."""
    root, run_dir = finished_run
    folder = tmp_path_factory.mktemp("binding") / "gallery"
    evaluate(folder.parent, run_dir / "best.pt", root, f"gallery.save={folder}")
    return root, run_dir / "best.pt", folder


def test_gallery_load_refuses_a_gallery_built_by_another_checkpoint(built, tmp_path):
    """It used to print the other weights' recall and exit 0: only the size and dim were compared."""
    root, ckpt, folder = built
    state = torch.load(ckpt, weights_only=True)
    name = next(k for k, v in state["task"].items() if v.is_floating_point())
    state["task"][name] = state["task"][name] + 0.01  # the same network, other weights
    torch.save(state, tmp_path / "other.pt")
    with pytest.raises(ConfigError, match=rf"gallery in {folder} was built with other weights \({ckpt}\) than "
                                          rf"{tmp_path / 'other.pt'}.*gallery.save={folder} gallery.overwrite=true"):
        evaluate(tmp_path, tmp_path / "other.pt", root, f"gallery.load={folder}")


def test_gallery_load_refuses_a_reordered_split_of_the_same_size(built, tmp_path):
    """It used to score the queries against rows that are other tiles (4/16/40 instead of 8/28/56) and exit 0."""
    root, ckpt, folder = built
    exact = evaluate(tmp_path, ckpt, root)
    assert evaluate(tmp_path, ckpt, root, f"gallery.load={folder}") == exact
    moved = tmp_path / "cvusa"
    shutil.copytree(root, moved)
    with pytest.raises(ConfigError, match=r"root '.*' \(gallery\) vs '.*cvusa' \(this evaluation\)"):
        evaluate(tmp_path, ckpt, moved, f"gallery.load={folder}")
    shutil.rmtree(moved)
    shutil.copytree(root, moved)  # the same folder, its val rows reversed
    split_csv = moved / "splits/val-19zl.csv"
    split_csv.write_text("".join(reversed(split_csv.read_text().splitlines(keepends=True))))
    gallery = tmp_path / "gallery"
    evaluate(tmp_path, ckpt, moved, f"gallery.save={gallery}")
    split_csv.write_text("".join(reversed(split_csv.read_text().splitlines(keepends=True))))  # reordered again
    with pytest.raises(ConfigError, match=rf"gallery in {gallery} was built from another split.*the reference "
                                          r"list: the same number of references, in another order"):
        evaluate(tmp_path, ckpt, moved, f"gallery.load={gallery}")


def test_an_existing_gallery_is_kept_unless_overwrite_before_any_data_is_read(built, tmp_path):
    root, ckpt, folder = built
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    with pytest.raises(ConfigError, match=rf"gallery.save={folder} already holds a gallery \(built by {ckpt} from "
                                          r"cvusa/val of .*\): add gallery.overwrite=true"):
        evaluate(tmp_path, ckpt, tmp_path / "no_such_dataset", f"gallery.save={folder}")  # refused before reading
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    copy = tmp_path / "gallery"
    shutil.copytree(folder, copy)
    info = json.loads((copy / "gallery.json").read_text())
    (copy / "gallery.json").write_text(json.dumps({**info, "reference_spread": 123.0}))
    evaluate(tmp_path, ckpt, root, f"gallery.save={copy}", "gallery.overwrite=true")
    assert json.loads((copy / "gallery.json").read_text())["reference_spread"] == info["reference_spread"]


def test_a_trained_kind_on_eight_references_is_refused_before_encoding(built, tmp_path, monkeypatch):
    from geoloc.tasks.crossview import gallery_build as crossview_gallery

    pytest.importorskip("faiss")
    root, ckpt, _ = built
    monkeypatch.setattr(crossview_gallery, "encode_split", lambda *a, **k: pytest.fail("encoded first"))
    with pytest.raises(ConfigError, match="gallery.kind=ivfpq builds ivfpq, which trains .* needs at least 256 "
                                          "references; this split has 8. Use gallery.kind=flat"):
        evaluate(tmp_path, ckpt, root, "gallery.backend=faiss", "gallery.kind=ivfpq", "gallery.m=8",
                 f"gallery.save={tmp_path / 'g'}")
    assert not (tmp_path / "g").exists()
