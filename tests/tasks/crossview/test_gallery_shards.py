"""A gallery built across jobs: a codebook trained once, shards encoded apart, one merge (geoloc/gallery/shards.py) that
gives the one-job gallery, and refuses shards that are missing, doubled or of another gallery. On given
descriptors: no network, no images."""

from __future__ import annotations

import json
import re
import shutil

import pytest
import torch
from geoloc.cli import main as geoloc
from geoloc.config import ConfigError
from geoloc.tasks.crossview import open_gallery
from geoloc.gallery import shards as gallery_shards
from geoloc.gallery.shards import merge_shards

from helpers.gallery_runs import META, gallery_evaluate, pairs_split
from helpers.faiss_threads import one_faiss_thread  # noqa: F401  (autouse)

N, DIM = 120, 32
KNOBS = dict(coarse_m=8, k_factor=8)
KIND_KNOBS = {"pq_sq8": KNOBS, "ivfpq_disk": dict(m=8, k_factor=8)}  # trained kinds, at 40-row shards


def descriptors(seed=0):
    g = torch.Generator().manual_seed(seed)
    reference = torch.nn.functional.normalize(torch.randn(N, DIM, generator=g), dim=1)
    query = torch.nn.functional.normalize(reference + 0.6 * torch.randn(N, DIM, generator=g), dim=1)
    return query, reference


def job(monkeypatch, tmp_path, meta=META, seed=0, split=None, **cfg):
    query, reference = descriptors(seed)
    return gallery_evaluate(monkeypatch, split or pairs_split(N, tmp_path / "data"), query, reference, meta=meta,
                            **cfg)


def shards(monkeypatch, tmp_path, kind, count=3, codebook=None, prefix="shard", **extra):
    """The shard folders of `count` jobs (a trained kind: filled from `codebook`)."""
    knobs = dict(backend="faiss", kind=kind, **{**KIND_KNOBS.get(kind, {}), **extra})
    folders = []
    for i in range(count):
        folder = tmp_path / f"{prefix}{i}"
        job(monkeypatch, tmp_path, save=str(folder), num_shards=count, shard_index=i,
            **({"codebook": str(codebook)} if codebook else {}), **knobs)
        folders.append(folder)
    return folders


def codebook_of(monkeypatch, tmp_path, name="codebook", seed=0, kind="pq_sq8"):
    folder = tmp_path / name
    job(monkeypatch, tmp_path, seed=seed, save=str(folder), train_only=True, backend="faiss", kind=kind,
        **KIND_KNOBS[kind])
    return folder


@pytest.mark.parametrize("kind", ["flat", "pq_sq8", "ivfpq_disk"])
def test_a_gallery_merged_from_three_shards_scores_exactly_as_the_one_job_gallery(monkeypatch, tmp_path, kind):
    pytest.importorskip("faiss")
    whole = tmp_path / "whole"
    job(monkeypatch, tmp_path, save=str(whole), backend="faiss", kind=kind, **KIND_KNOBS.get(kind, {}))
    codebook = codebook_of(monkeypatch, tmp_path, kind=kind) if kind in KIND_KNOBS else None
    folders = shards(monkeypatch, tmp_path, kind, codebook=codebook)
    assert [json.loads((f / "gallery.json").read_text())["num_references"] for f in folders] == [40, 40, 40]
    merged = tmp_path / "merged"
    assert geoloc(["gallery", "merge", *reversed(list(map(str, folders))), f"out={merged}"]) == 0  # any order

    one, joined = (open_gallery(f, META["model_fingerprint"], META["ckpt"]) for f in (whole, merged))
    assert joined.index.kind == kind and len(joined.index) == N
    query, _ = descriptors()
    (s1, r1), (s2, r2) = one.index.search(query, 10), joined.index.search(query, 10)
    torch.testing.assert_close(r2, r1, rtol=0, atol=0)
    torch.testing.assert_close(s2, s1, rtol=0, atol=0)
    assert joined.places.references == one.places.references
    assert joined.places.queries == one.places.queries
    assert joined.info["references_sha256"] == one.info["references_sha256"]
    assert joined.info["reference_spread"] == pytest.approx(one.info["reference_spread"], rel=1e-5)
    loaded = [job(monkeypatch, tmp_path, load=str(f)) for f in (whole, merged)]
    spreads = [m.pop("reference_spread") for m in loaded]  # float32 (one job) vs float64 moments (merge)
    assert loaded[0] == loaded[1] and 0 < loaded[0]["R@1"] < 1 and spreads[1] == pytest.approx(spreads[0], rel=1e-6)


def test_the_merge_refuses_missing_doubled_and_foreign_shards(monkeypatch, tmp_path):
    pytest.importorskip("faiss")
    codebook = codebook_of(monkeypatch, tmp_path)
    s0, s1, s2 = shards(monkeypatch, tmp_path, "pq_sq8", codebook=codebook)
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match=r"shard\(s\) 1 of 3 are missing \(given: 0: .*shard0, 2: .*shard2\): "
                                          r"encode them with .*gallery.shard_index=1"):
        merge_shards([s0, s2], out)
    with pytest.raises(ConfigError, match=rf"{s1} and {s1} both hold shard 1 of 3: give each shard once"):
        merge_shards([s0, s1, s1, s2], out)
    other = {**META, "ckpt": "/runs/b/best.pt", "model_fingerprint": "b" * 64}
    foreign = tmp_path / "foreign"
    with pytest.raises(ConfigError, match="other weights"):  # the codebook is bound to its weights too
        job(monkeypatch, tmp_path, meta=other, save=str(foreign), num_shards=3, shard_index=1,
            codebook=str(codebook), backend="faiss", kind="pq_sq8", **KNOBS)
    for name, differs in (("weights", "model_fingerprint"), ("split", "references_sha256"),
                          ("codebook", "codebook_sha256")):
        folder = tmp_path / f"foreign_{name}"
        if name == "weights":
            cb = tmp_path / "cb_weights"
            job(monkeypatch, tmp_path, meta=other, save=str(cb), train_only=True, backend="faiss", kind="pq_sq8",
                **KNOBS)
            job(monkeypatch, tmp_path, meta=other, save=str(folder), num_shards=3, shard_index=1,
                codebook=str(cb), backend="faiss", kind="pq_sq8", **KNOBS)
        elif name == "split":  # the same paths in another order: another reference list
            split = pairs_split(N, tmp_path / "data")
            split.references.reverse()
            cb = tmp_path / "cb_split"
            job(monkeypatch, tmp_path, split=split, save=str(cb), train_only=True, backend="faiss",
                kind="pq_sq8", **KNOBS)
            job(monkeypatch, tmp_path, split=split, save=str(folder), num_shards=3, shard_index=1, codebook=str(cb),
                backend="faiss", kind="pq_sq8", **KNOBS)
        else:  # a codebook trained again, on other descriptors
            cb = codebook_of(monkeypatch, tmp_path, "cb_other", seed=1)
            job(monkeypatch, tmp_path, save=str(folder), num_shards=3, shard_index=1, codebook=str(cb),
                backend="faiss", kind="pq_sq8", **KNOBS)
        with pytest.raises(ConfigError, match=rf"the shard in {folder} is not of the same gallery as the one in "
                                              rf"{s0}: {differs} .*rebuild the foreign one with"):
            merge_shards([s0, folder, s2], out)
    assert not out.exists()
    with pytest.raises(ConfigError, match=rf"{codebook} holds a codebook, not a shard"):
        merge_shards([s0, s1, s2, codebook], out)


def test_parts_are_refused_where_a_gallery_is_expected_and_shards_need_the_codebook(monkeypatch, tmp_path):
    pytest.importorskip("faiss")
    codebook = codebook_of(monkeypatch, tmp_path)
    (s0, *_) = shards(monkeypatch, tmp_path, "pq_sq8", codebook=codebook)
    for folder, what in ((s0, "shard 0 of 3"), (codebook, "the codebook")):
        with pytest.raises(ConfigError, match=rf"{folder} holds {what} of a gallery built across jobs, not a whole "
                                              r"gallery: join the shards first \(geoloc gallery merge"):
            open_gallery(folder, META["model_fingerprint"], META["ckpt"])
    with pytest.raises(ConfigError, match=r"builds pq_sq8, which trains a codebook, and each shard must be filled "
                                          r"from the same one: build it once with gallery.train_only=true"):
        shards(monkeypatch, tmp_path, "pq_sq8", prefix="no_codebook")
    with pytest.raises(ConfigError, match=r"trained for another index: coarse_m 8 \(codebook\) vs 4 \(here\)"):
        shards(monkeypatch, tmp_path, "pq_sq8", codebook=codebook, prefix="other_knobs", coarse_m=4)


def test_bad_merge_arguments_get_a_clean_message_and_exit_2(monkeypatch, tmp_path, capsys):
    """A missing path, an unmatched glob, a file, a shard without gallery.faiss, a record without
    reference_moments: each was a raw traceback."""
    folders = shards(monkeypatch, tmp_path, "flat", count=2)
    file = tmp_path / "notes.txt"
    file.write_text("not a shard")
    no_faiss, no_moments = tmp_path / "no_faiss", tmp_path / "no_moments"
    shutil.copytree(folders[1], no_faiss)
    (no_faiss / "gallery.faiss").unlink()
    shutil.copytree(folders[1], no_moments)
    info = json.loads((no_moments / "gallery.json").read_text())
    del info["reference_moments"]
    (no_moments / "gallery.json").write_text(json.dumps(info))
    cases = {tmp_path / "nope": "no such folder",
             tmp_path / "shards" / "*": r"matched no folder \(the shell passes a pattern that matches nothing as it is\)",
             file: "is a file, not a shard folder",
             no_faiss: r"its index file .*gallery.faiss is missing. Rebuild it with python evaluate.py",
             no_moments: r"gallery.json lacks reference_moments .*Rebuild it with python evaluate.py"}
    out = tmp_path / "out"
    for bad, says in cases.items():
        assert geoloc(["gallery", "merge", str(folders[0]), str(bad), f"out={out}"]) == 2, bad
        err = capsys.readouterr().err
        assert err.startswith("geoloc gallery: ") and str(bad) in err and re.search(says, err), err
    assert not out.exists()


def test_an_out_folder_among_the_shards_is_refused_before_any_work(monkeypatch, tmp_path, capsys):
    """out=s0 overwrite=true replaced shard s0 with the merged gallery, and s0's block had to be encoded again."""
    folders = shards(monkeypatch, tmp_path, "flat", count=2)
    before = {f: {p.name: p.read_bytes() for p in f.iterdir()} for f in folders}
    loads = []
    monkeypatch.setattr(gallery_shards.GalleryIndex, "load", lambda *a, **k: loads.append(a))
    for out, what in ((folders[0], "is the shard folder"), (folders[1] / "merged", "is inside the shard folder"),
                      (tmp_path, "holds the shard folder")):
        args = ["gallery", "merge", *map(str, folders), f"out={out}", "overwrite=true"]
        assert geoloc(args) == 2, out
        err = capsys.readouterr().err
        assert f"geoloc gallery: out={out} {what} " in err and "outside the shards" in err, err
    assert not loads  # refused before any index was read
    assert {f: {p.name: p.read_bytes() for p in f.iterdir()} for f in folders} == before


@pytest.mark.parametrize("backend, kind, copied", [("faiss", "flat", "gallery.faiss"), ("torch", "flat", "gallery.pt"),
                                                   ("faiss", "ivfpq_disk", "gallery.0.f16")])
def test_a_shard_whose_index_file_came_from_another_shard_is_refused(monkeypatch, tmp_path, backend, kind, copied):
    """Two shards of one row count: shard 2's index file copied from shard 1 merged with exit 0, and the recall was
    wrong. Each shard's gallery.json records the digest of its own index files (an ivfpq_disk's float16 rows
    too)."""
    codebook = {"codebook": str(codebook_of(monkeypatch, tmp_path, kind=kind))} if kind in KIND_KNOBS else {}
    folders = []
    for i in range(3):
        folders.append(tmp_path / f"shard{i}")
        job(monkeypatch, tmp_path, save=str(folders[-1]), num_shards=3, shard_index=i, backend=backend, kind=kind,
            **codebook, **KIND_KNOBS.get(kind, {}))
    shutil.copyfile(folders[1] / copied, folders[2] / copied)
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match=rf"the shard in {folders[2]}: its index file {folders[2] / copied} is not "
                                          r"the one its shard job wrote \(its sha256 differs from the one "
                                          r".*gallery.json records\).*Rebuild it with"):
        merge_shards(folders, out)
    assert not out.exists()
