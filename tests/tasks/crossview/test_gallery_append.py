"""`geoloc gallery append`: new references added to a gallery without a rebuild, filled from its codebook; the
binding to the reference list updated; foreign or repeated parts refused."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from geoloc.cli import main as geoloc
from geoloc.config import ConfigError
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval import GalleryIndex
from geoloc.gallery import append_galleries, merge_shards, open_gallery
from geoloc.gallery.places import reference_paths_sha256
from helpers.faiss_threads import one_faiss_thread  # noqa: F401  (autouse)
from helpers.gallery_runs import META, gallery_evaluate

DIM = 32
KNOBS = {"pq_sq8": dict(coarse_m=8, k_factor=8), "ivfpq_disk": dict(m=8, k_factor=8)}


def area(tmp_path, name, n, seed):
    """A one-to-one split of `n` pairs under its own root, and its descriptors."""
    g = torch.Generator().manual_seed(seed)
    reference = torch.nn.functional.normalize(torch.randn(n, DIM, generator=g), dim=1)
    query = torch.nn.functional.normalize(reference + 0.6 * torch.randn(n, DIM, generator=g), dim=1)
    split = RetrievalSplit(name, tmp_path / name, [f"q{i}.jpg" for i in range(n)], [f"r{i}.jpg" for i in range(n)],
                           np.arange(n))
    return split, query, reference


def build(monkeypatch, tmp_path, kind, codebook=None, shards=2, meta=META, name="a", n=120, seed=0):
    """The shard folders of area `name` (filled from `codebook`, trained here on area a when None)."""
    split, query, reference = area(tmp_path, name, n, seed)
    knobs = dict(backend="faiss", kind=kind, **KNOBS[kind])
    if codebook is None:
        codebook = tmp_path / "codebook"
        gallery_evaluate(monkeypatch, split, query, reference, meta=meta, save=str(codebook), train_only=True, **knobs)
    folders = []
    for i in range(shards):
        folders.append(tmp_path / f"{name}_shard{i}")
        gallery_evaluate(monkeypatch, split, query, reference, meta=meta, save=str(folders[-1]), num_shards=shards,
                         shard_index=i, codebook=str(codebook), **knobs)
    return codebook, folders, split, query, reference


@pytest.mark.parametrize("kind", ["pq_sq8", "ivfpq_disk"])
def test_appended_parts_search_as_one_index_filled_from_the_codebook_and_the_binding_follows(monkeypatch, tmp_path,
                                                                                             kind):
    codebook, a_shards, split_a, query_a, reference_a = build(monkeypatch, tmp_path, kind)
    merge_shards(a_shards, tmp_path / "gallery")
    _, b_parts, split_b, query_b, reference_b = build(monkeypatch, tmp_path, kind, codebook, name="b", n=80, seed=1)
    assert geoloc(["gallery", "append", str(tmp_path / "gallery"), *map(str, b_parts), f"out={tmp_path / 'grown'}"]) == 0

    grown = open_gallery(tmp_path / "grown", META["model_fingerprint"], META["ckpt"])  # as localize.py opens it
    whole = GalleryIndex.load(codebook / "gallery.pt", mmap=False).trained_empty()
    whole.add(reference_a).add(reference_b)
    queries = torch.cat([query_a, query_b])
    torch.testing.assert_close(grown.index.search(queries, 10), whole.search(queries, 10), rtol=0, atol=0)
    # the part's references follow the gallery's, on the gallery's root (b's files lie outside it: absolute paths)
    paths = [f"r{i}.jpg" for i in range(120)] + [str(tmp_path / "b" / f"r{i}.jpg") for i in range(80)]
    assert grown.places.references == paths
    assert grown.info["references_sha256"] == reference_paths_sha256(paths) and grown.info["num_references"] == 200
    assert [(r["split"], r["num_references"], r["whole_split"]) for r in grown.info["appended"]] == [("b", 40, False),
                                                                                                    ("b", 40, False)]
    with pytest.raises(ConfigError, match=r"built from another split than the one scored here: .*it holds "
                                          r"references appended from 2 other part\(s\)"):
        open_gallery(tmp_path / "grown", META["model_fingerprint"], META["ckpt"], split=split_a, dataset="pairs")
    if kind == "ivfpq_disk":  # the rows already on disk are linked into the grown gallery, not written again
        rows = sorted((tmp_path / "grown").glob("*.f16"))
        sources = [tmp_path / "gallery" / "gallery.0.f16", tmp_path / "gallery" / "gallery.1.f16",
                   b_parts[0] / "gallery.0.f16", b_parts[1] / "gallery.0.f16"]
        assert [r.stat().st_ino for r in rows] == [s.stat().st_ino for s in sources]


def test_in_place_append_and_the_refusals(monkeypatch, tmp_path):
    codebook, a_shards, *_ = build(monkeypatch, tmp_path, "ivfpq_disk")
    gallery = tmp_path / "gallery"
    merge_shards(a_shards, gallery)
    _, b_parts, *_ = build(monkeypatch, tmp_path, "ivfpq_disk", codebook, name="b", n=80, seed=1)
    with pytest.raises(ConfigError, match=r"lists 40 reference\(s\) that another part holds already"):
        append_galleries(gallery, [b_parts[0], b_parts[0]], tmp_path / "twice")
    with pytest.raises(ConfigError, match=r"holds r0.jpg already, which a part lists again"):
        append_galleries(gallery, [a_shards[0]], tmp_path / "again")
    with pytest.raises(ConfigError, match=r"holds a codebook, not references"):
        append_galleries(gallery, [codebook], tmp_path / "codebook_part")
    with pytest.raises(ConfigError, match=r"holds a part of a gallery, not a gallery"):
        append_galleries(a_shards[0], b_parts, tmp_path / "from_shard")
    other = {**META, "model_fingerprint": "b" * 64}
    other_cb = tmp_path / "other"
    other_cb.mkdir()
    _, foreign, *_ = build(monkeypatch, other_cb, "ivfpq_disk", meta=other, name="c", n=80, seed=2)
    with pytest.raises(ConfigError, match=r"cannot be appended to the gallery in .*model_fingerprint"):
        append_galleries(gallery, foreign[:1], tmp_path / "foreign")
    assert not any((tmp_path / n).exists() for n in ("twice", "again", "codebook_part", "from_shard", "foreign"))

    before = json.loads((gallery / "gallery.json").read_text())["num_references"]
    append_galleries(gallery, b_parts, gallery, overwrite=True)  # in place
    grown = open_gallery(gallery, META["model_fingerprint"], META["ckpt"])
    assert (before, len(grown.index)) == (120, 200)
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no temporary folder left behind


def test_a_gallery_that_trained_its_own_codebook_says_how_to_build_one_that_can_grow(monkeypatch, tmp_path):
    split, query, reference = area(tmp_path, "a", 120, 0)
    gallery_evaluate(monkeypatch, split, query, reference, save=str(tmp_path / "one_job"), backend="faiss",
                     kind="pq_sq8", **KNOBS["pq_sq8"])
    with pytest.raises(ConfigError, match=r"trained its own codebook in one job, so no part can be filled from it"):
        append_galleries(tmp_path / "one_job", [tmp_path], tmp_path / "out")
