"""The approximate FAISS gallery kinds (pq_refine, ivfpq_refine, pq_sq8, ivfpq_disk, hnsw), galleries merged from parts, and
gallery.kind in GalleryConfig."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from geoloc.config import ConfigError
from geoloc.eval import GalleryIndex
from geoloc.gallery.index_settings import GalleryConfig, build_index
from helpers.descriptor_data import low_rank_pairs
from helpers.faiss_threads import one_faiss_thread  # noqa: F401  (autouse)

faiss = pytest.importorskip("faiss")

DIM = 32
SMALL = dict(nlist=16, m=8, coarse_m=8, nprobe=8, k_factor=8, hnsw_m=16, ef_construction=40, ef_search=64)
NEW_KINDS = ["pq_refine", "ivfpq_refine", "hnsw"]


def unit(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def easy():
    """5,000 references of intrinsic dimension 8 in 32-D; query i = reference i plus a little noise."""
    return low_rank_pairs(5000, 300, DIM, noise=0.2, seed=0)


def exact_top(query, reference, k):
    sim = query.astype(np.float64) @ reference.astype(np.float64).T
    return np.argsort(-sim, axis=1, kind="stable")[:, :k]


def faiss_knobs(index: GalleryIndex) -> dict:
    """The search knobs as the FAISS objects hold them (not as ``params`` says)."""
    inner = faiss.downcast_index(index._index)
    knobs = {}
    if index.kind in ("pq_refine", "ivfpq_refine", "pq_sq8"):
        knobs["k_factor"] = inner.k_factor
        inner = faiss.downcast_index(inner.base_index)
    if index.kind in ("ivfpq", "ivfpq_refine", "ivfpq_disk"):
        knobs["nprobe"] = inner.nprobe
    if index.kind == "hnsw":
        knobs["ef_search"] = inner.hnsw.efSearch
    return knobs


@pytest.mark.parametrize("kind", NEW_KINDS)
def test_new_kind_keeps_the_exact_top1_and_returns_exact_inner_products(easy, kind):
    query, reference = easy
    index = GalleryIndex(DIM, backend="faiss", kind=kind, **SMALL).add(reference)
    scores, rows = index.search(query, 10)
    # Scores are the inner products of the unit descriptors of the rows returned (exact re-ranking / flat storage).
    brute = np.einsum("qd,qkd->qk", query.astype(np.float64), reference[rows.numpy()].astype(np.float64))
    np.testing.assert_allclose(scores.numpy(), brute, atol=1e-5)
    assert (np.diff(scores.numpy(), axis=1) <= 1e-6).all()  # best first
    top1_kept = np.mean(rows.numpy()[:, 0] == exact_top(query, reference, 1)[:, 0])
    assert top1_kept >= 0.97, f"{kind} kept only {top1_kept:.3f} of the exact top-1"


def test_refine_rescores_what_ivfpq_only_estimates(easy):
    query, reference = easy
    scores, rows = GalleryIndex(DIM, backend="faiss", kind="ivfpq", nbits=4, **SMALL).add(reference).search(query, 5)
    brute = np.einsum("qd,qkd->qk", query, reference[rows.numpy()])
    assert np.abs(scores.numpy() - brute).max() > 1e-3  # PQ estimates: the refine test above has teeth


def test_pq_sq8_keeps_the_exact_top1_from_a_quarter_of_the_bytes(easy, tmp_path):
    query, reference = easy
    index = GalleryIndex(DIM, backend="faiss", kind="pq_sq8", **SMALL).add(reference)
    scores, rows = index.search(query, 10)
    brute = np.einsum("qd,qkd->qk", query.astype(np.float64), reference[rows.numpy()].astype(np.float64))
    np.testing.assert_allclose(scores.numpy(), brute, atol=5e-3)  # SQ8 estimates of the rows' inner products
    assert (np.diff(scores.numpy(), axis=1) <= 1e-6).all()
    top1_kept = np.mean(rows.numpy()[:, 0] == exact_top(query, reference, 1)[:, 0])
    assert top1_kept >= 0.97, f"pq_sq8 kept only {top1_kept:.3f} of the exact top-1"
    index.save(tmp_path / "gallery.pt")
    per_reference = (tmp_path / "gallery.faiss").stat().st_size / len(reference)
    # one byte a dimension (SQ8) and coarse_m / 2 bytes of 4-bit codes, plus the codebooks spread over the rows
    assert DIM + SMALL["coarse_m"] / 2 <= per_reference < DIM + SMALL["coarse_m"] / 2 + 2, per_reference


@pytest.mark.parametrize("kind", ["flat", "pq_sq8", "ivfpq_refine", "ivfpq_disk", "torch"])
def test_a_gallery_merged_from_parts_filled_from_one_codebook_equals_the_one_built_whole(easy, kind):
    query, reference = easy
    backend, kind = ("torch", "flat") if kind == "torch" else ("faiss", kind)
    whole = GalleryIndex(DIM, backend=backend, kind=kind, **SMALL).add(reference)
    codebook = GalleryIndex(DIM, backend=backend, kind=kind, **SMALL)
    codebook.train(reference)
    parts = [codebook.trained_empty().add(reference[s:s + 1700]) for s in range(0, len(reference), 1700)]
    assert len(codebook) == 0 and [len(p) for p in parts] == [1700, 1700, 1600]
    merged = parts[0]
    for part in parts[1:]:
        merged.merge(part)
    assert len(merged) == len(reference)
    (s1, r1), (s2, r2) = whole.search(query, 10), merged.search(query, 10)
    torch.testing.assert_close(r2, r1, rtol=0, atol=0)
    torch.testing.assert_close(s2, s1, rtol=0, atol=0)
    with pytest.raises(ValueError, match="cannot merge"):
        merged.merge(GalleryIndex(DIM + 8, backend=backend, kind=kind, **SMALL))


@pytest.mark.parametrize("kind", ["ivfpq", *NEW_KINDS, "pq_sq8", "ivfpq_disk"])
def test_save_load_round_trip_keeps_results_and_search_knobs(easy, tmp_path, kind):
    query, reference = easy
    index = GalleryIndex(DIM, backend="faiss", kind=kind, nbits=4, **SMALL).add(reference)
    index.set_search_params(nprobe=3, k_factor=2, ef_search=17)  # away from the defaults the loader starts from
    before = index.search(query, 10)
    index.save(tmp_path / "gallery.pt")
    loaded = GalleryIndex.load(tmp_path / "gallery.pt")
    assert loaded.params == index.params and loaded.kind == kind and len(loaded) == len(reference)
    assert faiss_knobs(loaded) == faiss_knobs(index) != {}
    after = loaded.search(query, 10)
    torch.testing.assert_close(after[1], before[1])
    torch.testing.assert_close(after[0], before[0])


def test_search_knobs_reach_faiss_and_change_the_search(easy):
    query, reference = easy
    index = GalleryIndex(DIM, backend="faiss", kind="ivfpq_refine", **SMALL).add(reference)
    wide = index.search(query, 1)[1]
    index.set_search_params(nprobe=1, k_factor=1)
    assert faiss_knobs(index) == {"nprobe": 1, "k_factor": 1.0}
    assert (index.search(query, 1)[1] != wide).any()
    with pytest.raises(ValueError, match="nprobe, k_factor and ef_search"):
        index.set_search_params(efSearch=10)
    with pytest.raises(ValueError, match="k_factor=0"):
        index.set_search_params(k_factor=0)


def test_bad_kind_and_parameters_are_named():
    with pytest.raises(ValueError, match="'annoy'"):
        GalleryIndex(DIM, backend="faiss", kind="annoy")
    with pytest.raises(ValueError, match="hnsw.*for torch"):
        GalleryIndex(DIM, backend="torch", kind="hnsw")
    with pytest.raises(ValueError, match="m .*divide dim, got dim=32, m=5"):
        GalleryIndex(DIM, backend="faiss", kind="pq_refine", m=5)
    with pytest.raises(ValueError, match="ef_search=0"):
        GalleryIndex(DIM, backend="faiss", kind="hnsw", ef_search=0)
    with pytest.raises(ValueError, match="k_factor=2.5"):
        GalleryIndex(DIM, backend="faiss", kind="pq_refine", k_factor=2.5)


def test_gallery_config_kind_auto_and_errors():
    cfg = GalleryConfig()
    assert cfg.kind == "auto"
    assert cfg.resolved(cfg.auto_exact_below - 1, 512) == ("torch", "flat")
    assert cfg.resolved(cfg.auto_exact_below, 512) == ("faiss", "pq_refine")
    assert GalleryConfig(backend="faiss", kind="hnsw").resolved(10, 512) == ("faiss", "hnsw")
    # the float32 vectors of 4M x 512 are 8 GiB: pq_refine keeps them; one reference more and pq_sq8 is built
    assert cfg.max_memory == "8GiB" and cfg.resolved(4 * 2**20, 512) == ("faiss", "pq_refine")
    assert cfg.resolved(4 * 2**20 + 1, 512) == ("faiss", "pq_sq8")
    # pq_sq8 holds 512 + 16 bytes a reference: 16,268,009 of them fit in 8 GiB, one more goes to disk
    assert cfg.resolved(8 * 2**30 // 528, 512) == ("faiss", "pq_sq8")
    assert cfg.resolved(8 * 2**30 // 528 + 1, 512) == ("faiss", "ivfpq_disk")
    assert GalleryConfig(max_memory="100MB").resolved(cfg.auto_exact_below, 256) == ("faiss", "pq_sq8")  # 102 MB
    assert GalleryConfig(max_memory="103MB").resolved(cfg.auto_exact_below, 256) == ("faiss", "pq_refine")
    assert GalleryConfig(max_memory=102_400_000).resolved(cfg.auto_exact_below, 256) == ("faiss", "pq_refine")
    for bad in ("8 GiBs", "-1GB", "lots", "0"):
        with pytest.raises(ValueError, match=rf"gallery.max_memory={bad!r}: give a size such as 8GiB"):
            GalleryConfig(max_memory=bad)
    with pytest.raises(ValueError, match="gallery.kind must be one of"):
        GalleryConfig(kind="ivf")
    with pytest.raises(ValueError, match="gallery.kind=pq_refine needs gallery.backend=faiss"):
        GalleryConfig(kind="pq_refine")
    with pytest.raises(ValueError, match="gallery.ef_search=0"):
        GalleryConfig(backend="faiss", kind="hnsw", ef_search=0)


def test_build_index_auto_switches_to_pq_refine_at_the_threshold(easy):
    _, reference = easy
    ref = torch.from_numpy(reference)
    assert build_index(ref, GalleryConfig(auto_exact_below=5001)).kind == "flat"
    index = build_index(ref, GalleryConfig(auto_exact_below=5000, m=8))
    assert (index.backend, index.kind, len(index)) == ("faiss", "pq_refine", 5000)
    with pytest.raises(ConfigError, match="gallery.m=5 .* divide the descriptor dim 32"):
        build_index(ref, GalleryConfig(auto_exact_below=100, m=5))


def test_query_blocks_give_the_one_call_result(easy, monkeypatch):
    import geoloc.eval.search_index as gallery_mod

    query, reference = easy
    index = GalleryIndex(DIM, backend="faiss", kind="pq_refine", **SMALL).add(reference)
    whole = index.search(query, 10)
    monkeypatch.setattr(gallery_mod, "SCORE_BUDGET", 7 * 10 * SMALL["k_factor"])  # 300 queries in 43 calls
    blocked = index.search(query, 10)
    torch.testing.assert_close(blocked[1], whole[1])
    torch.testing.assert_close(blocked[0], whole[0])


@pytest.mark.parametrize("kind, needed", [("ivfpq", 256), ("pq_refine", 16), ("ivfpq_refine", 16)])
def test_a_trained_kind_refuses_too_few_vectors_with_the_count_it_needs(kind, needed):
    """FAISS's own error ("Number of training points (25) should be at least as large as number of clusters")
    names neither the kind nor the way out."""
    reference = torch.from_numpy(unit(np.random.default_rng(0).standard_normal((needed - 1, DIM)))).float()
    with pytest.raises(ValueError, match=rf"the {kind} index trains .* at least {needed} descriptors to train on, "
                                         rf"got {needed - 1}: use kind='flat'"):
        GalleryIndex(DIM, backend="faiss", kind=kind, m=8, nlist=1).add(reference)
    full = torch.cat([reference, reference[:1]])
    assert len(GalleryIndex(DIM, backend="faiss", kind=kind, m=8, nlist=1).add(full)) == needed  # the bound is tight


@pytest.mark.parametrize("backend", ["torch", "faiss"])
def test_a_truncated_or_corrupt_index_file_is_named(tmp_path, backend):
    reference = torch.from_numpy(unit(np.random.default_rng(0).standard_normal((50, DIM)))).float()
    GalleryIndex(DIM, backend=backend).add(reference).save(tmp_path / "gallery.pt")
    data = (tmp_path / "gallery.pt").read_bytes()
    (tmp_path / "gallery.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=rf"could not read the gallery index {tmp_path / 'gallery.pt'}: it is "
                                         r"truncated, corrupt or not a gallery.pt \("):
        GalleryIndex.load(tmp_path / "gallery.pt")
    if backend == "faiss":  # a readable archive whose FAISS index is cut
        GalleryIndex(DIM, backend=backend).add(reference).save(tmp_path / "gallery.pt")
        blob = tmp_path / "gallery.faiss"
        data = blob.read_bytes()
        blob.write_bytes(data[:100])
        with pytest.raises(ValueError, match=rf"the gallery index {tmp_path / 'gallery.pt'} is corrupt .*"
                                             rf"{blob} holds 100 bytes, {len(data)} were written"):
            GalleryIndex.load(tmp_path / "gallery.pt")
        blob.write_bytes(b"\0" * len(data))  # as long as written, but not a FAISS index
        with pytest.raises(ValueError, match=rf"the gallery index {tmp_path / 'gallery.pt'} is corrupt \("):
            GalleryIndex.load(tmp_path / "gallery.pt")


def test_a_memory_mapped_index_refuses_to_change_instead_of_aborting(easy, tmp_path):
    query, reference = easy
    GalleryIndex(DIM, backend="faiss", kind="pq_sq8", **SMALL).add(reference).save(tmp_path / "gallery.pt")
    mapped = GalleryIndex.load(tmp_path / "gallery.pt")
    writable = GalleryIndex.load(tmp_path / "gallery.pt", mmap=False)
    for change in (lambda: mapped.add(reference[:5]), mapped.trained_empty, lambda: mapped.merge(writable),
                   lambda: writable.merge(mapped)):
        with pytest.raises(ValueError, match=r"memory-mapped from its file: load it with .*mmap=False"):
            change()
    assert len(mapped.search(query, 3)[1]) == len(query)
    writable.merge(GalleryIndex.load(tmp_path / "gallery.pt", mmap=False))
    assert len(writable) == 2 * len(reference) and len(writable.trained_empty()) == 0


@pytest.mark.parametrize("kind, part", [("pq_sq8", "outer"), ("pq_sq8", "base_index"), ("pq_refine", "outer"),
                                        ("ivfpq_refine", "base_index"), ("ivfpq", "outer")])
def test_an_index_whose_parts_disagree_is_refused_when_it_is_opened(easy, tmp_path, kind, part):
    """An outer index counting other rows than the parts it wraps opened, then every search raised FAISS's
    RuntimeError (a 500 on every request of a service that had started cleanly)."""
    from geoloc.eval.index_structure import index_parts

    _, reference = easy
    index = GalleryIndex(DIM, backend="faiss", kind=kind, **SMALL).add(reference[:600])
    index_parts(faiss, index._index)[part].ntotal -= 10
    index.save(tmp_path / "gallery.pt")
    with pytest.raises(ValueError, match=rf"the gallery index {tmp_path / 'gallery.pt'} is corrupt .*"
                                         rf"{tmp_path / 'gallery.faiss'} holds a FAISS index whose parts disagree: "
                                         rf"its record gives dimension {DIM} and the outer index holds"):
        GalleryIndex.load(tmp_path / "gallery.pt")


def test_an_index_file_of_another_kind_is_refused_when_it_is_opened(easy, tmp_path):
    _, reference = easy
    GalleryIndex(DIM, backend="faiss", kind="pq_sq8", **SMALL).add(reference[:600]).save(tmp_path / "gallery.pt")
    GalleryIndex(DIM, backend="faiss", kind="flat").add(reference[:600]).save(tmp_path / "flat.pt")
    state = torch.load(tmp_path / "gallery.pt", weights_only=True)
    (tmp_path / "flat.faiss").replace(tmp_path / "gallery.faiss")
    torch.save({**state, "faiss_bytes": (tmp_path / "gallery.faiss").stat().st_size}, tmp_path / "gallery.pt")
    with pytest.raises(ValueError, match=r"gallery.faiss holds a FAISS index of parts \{'outer': 'IndexFlatIP'\}, "
                                         r"where its record's kind has \{'outer': 'IndexRefine', 'base_index': "
                                         r"'IndexPQFastScan', 'refine_index': 'IndexScalarQuantizer'\}"):
        GalleryIndex.load(tmp_path / "gallery.pt")
