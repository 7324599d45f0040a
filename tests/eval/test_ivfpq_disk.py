"""ivfpq_disk: IVF-PQ codes in memory, the shortlist re-ranked from float16 rows memory-mapped from disk."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geoloc.eval import GalleryIndex
from geoloc.eval.half_vectors import HalfVectors
from helpers.descriptor_data import low_rank_pairs
from helpers.faiss_threads import one_faiss_thread  # noqa: F401  (autouse)

faiss = pytest.importorskip("faiss")

DIM = 32


def unit(x):
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


@pytest.fixture(scope="module")
def data():
    """4,000 references of intrinsic dimension 8 in 32-D; query i = reference i plus noise."""
    return low_rank_pairs(4000, 200, DIM, noise=0.3, seed=1)


def brute_force(query, reference, k):
    """The top-k of every query over the float16 rows, scored in float64, the lower row first among ties."""
    half = reference.astype(np.float16).astype(np.float64)
    sim = query.astype(np.float64) @ half.T
    rows = np.argsort(-sim, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(sim, rows, 1), rows


def test_with_every_list_probed_and_every_row_shortlisted_it_is_the_brute_force_over_the_float16_rows(data):
    query, reference = data
    index = GalleryIndex(DIM, backend="faiss", kind="ivfpq_disk", nlist=16, m=8, nprobe=16, k_factor=400)
    index.add(reference)  # shortlist 10 x 400 = every row, from all 16 lists
    scores, rows = index.search(query, 10)
    want_scores, want_rows = brute_force(query, reference, 10)
    np.testing.assert_array_equal(rows.numpy(), want_rows)
    np.testing.assert_allclose(scores.numpy(), want_scores, atol=1e-5)


def test_the_default_shortlist_keeps_the_exact_top1_where_the_codes_alone_do_not(data):
    query, reference = data
    knobs = dict(nlist=16, m=4, nbits=4, nprobe=4)  # coarse codes: their own ranking loses the top-1 often
    exact = brute_force(query, reference, 1)[1][:, 0]
    codes = GalleryIndex(DIM, backend="faiss", kind="ivfpq", **knobs).add(reference).search(query, 10)[1]  # 4-bit
    disk_scores, disk = GalleryIndex(DIM, backend="faiss", kind="ivfpq_disk", **knobs).add(reference).search(query, 10)
    kept_codes, kept_disk = np.mean(codes[:, 0].numpy() == exact), np.mean(disk[:, 0].numpy() == exact)
    assert kept_disk >= 0.95 and kept_disk > kept_codes + 0.1, (kept_codes, kept_disk)
    # the scores returned are the float16 rows' inner products, within float16 rounding of the exact ones
    rows = disk.numpy()
    exact_scores = np.einsum("qd,qkd->qk", query.astype(np.float64), reference[rows].astype(np.float64))
    np.testing.assert_allclose(disk_scores.numpy(), exact_scores, atol=2e-3)


def test_saved_it_holds_the_codes_beside_two_bytes_a_dimension_and_maps_them_back(data, tmp_path):
    query, reference = data
    index = GalleryIndex(DIM, backend="faiss", kind="ivfpq_disk", nlist=16, m=8).add(reference)
    index.save(tmp_path / "gallery.pt")
    assert (tmp_path / "gallery.0.f16").stat().st_size == len(reference) * DIM * 2
    per_reference = (tmp_path / "gallery.faiss").stat().st_size / len(reference)
    codebooks = (16 * DIM + 16 * DIM) * 4 / len(reference)  # the 4-bit PQ centroids and the 16 lists' centroids
    # m 4-bit codes and an 8-byte row number a reference, plus the codebooks spread over the rows (and each
    # list's codes padded to a block of 32)
    assert 4 + 8 + codebooks <= per_reference < 4 + 8 + codebooks + 1, per_reference
    loaded = GalleryIndex.load(tmp_path / "gallery.pt")
    assert all(isinstance(block, np.memmap) for block in loaded._half._blocks)  # read as searches touch it
    torch.testing.assert_close(loaded.search(query, 5), index.search(query, 5), rtol=0, atol=0)


@pytest.mark.parametrize("damage", ["missing", "truncated"])
def test_a_missing_or_cut_float16_file_is_named_when_the_gallery_is_opened(data, tmp_path, damage):
    _, reference = data
    GalleryIndex(DIM, backend="faiss", kind="ivfpq_disk", nlist=16, m=8).add(reference).save(tmp_path / "g.pt")
    rows = tmp_path / "g.0.f16"
    if damage == "missing":
        rows.unlink()
    else:
        rows.write_bytes(rows.read_bytes()[:-2])
    with pytest.raises(ValueError, match=r"g\.0\.f16"):
        GalleryIndex.load(tmp_path / "g.pt")


def test_half_vectors_gather_rows_across_blocks_in_the_order_asked(tmp_path):
    rng = np.random.default_rng(0)
    rows = rng.standard_normal((50, 4)).astype(np.float32)
    vectors = HalfVectors(4)
    for s in (0, 7, 30):  # three blocks of 7, 23 and 20 rows
        vectors.append(rows[s:{0: 7, 7: 30, 30: 50}[s]])
    wanted = np.array([49, 0, 7, 6, 30, 29, 7])
    np.testing.assert_array_equal(vectors.gather(wanted), rows[wanted].astype(np.float16).astype(np.float32))
    files = vectors.write(tmp_path / "v")
    assert files == [["v.0.f16", 50]]  # the blocks held in memory: one file
    mapped = HalfVectors.open(tmp_path, files, 4)
    np.testing.assert_array_equal(mapped.gather(wanted), vectors.gather(wanted))
    with pytest.raises(IndexError):
        vectors.gather(np.array([50]))


def test_a_merge_links_the_shards_rows_instead_of_writing_them_again(data, tmp_path):
    query, reference = data
    codebook = GalleryIndex(DIM, backend="faiss", kind="ivfpq_disk", nlist=16, m=8)
    codebook.train(reference)
    for i, s in enumerate((0, 1500)):
        codebook.trained_empty().add(reference[s:s + 1500] if s == 0 else reference[s:]).save(tmp_path / f"s{i}.pt")
    merged = GalleryIndex.load(tmp_path / "s0.pt", mmap=False).merge(GalleryIndex.load(tmp_path / "s1.pt", mmap=False))
    (tmp_path / "out").mkdir()
    merged.save(tmp_path / "out" / "gallery.pt")
    written = sorted(p.name for p in (tmp_path / "out").glob("*.f16"))
    assert written == ["gallery.0.f16", "gallery.1.f16"]
    for i in (0, 1):  # the same files on disk, not copies
        assert (tmp_path / "out" / f"gallery.{i}.f16").stat().st_ino == (tmp_path / f"s{i}.0.f16").stat().st_ino
    whole = GalleryIndex(DIM, backend="faiss", kind="ivfpq_disk", nlist=16, m=8)
    whole.train(reference)
    whole.add(reference)
    loaded = GalleryIndex.load(tmp_path / "out" / "gallery.pt")
    torch.testing.assert_close(loaded.search(query, 10), whole.search(query, 10), rtol=0, atol=0)


def test_a_saved_ivfpq_disk_gallery_is_refused_to_other_weights_a_reordered_split_and_with_a_cut_rows_file(
        monkeypatch, tmp_path):
    from geoloc.config import ConfigError
    from geoloc.gallery import open_gallery
    from helpers.gallery_runs import META, gallery_evaluate, pairs_split

    rng = np.random.default_rng(0)
    reference = torch.from_numpy(unit(rng.standard_normal((120, DIM)).astype(np.float32)))
    split = pairs_split(120, tmp_path / "data")
    folder = tmp_path / "gallery"
    gallery_evaluate(monkeypatch, split, reference, reference, save=str(folder), backend="faiss", kind="ivfpq_disk",
                     m=8)
    assert len(open_gallery(folder, META["model_fingerprint"], META["ckpt"], split=split, dataset="pairs").index) == 120
    with pytest.raises(ConfigError, match="was built with other weights"):
        open_gallery(folder, "b" * 64, META["ckpt"])
    split.references.reverse()
    with pytest.raises(ConfigError, match=r"another split .*references_sha256 differs"):
        open_gallery(folder, META["model_fingerprint"], META["ckpt"], split=split, dataset="pairs")
    rows = folder / "gallery.0.f16"
    rows.write_bytes(rows.read_bytes()[:-64])
    with pytest.raises(ConfigError, match=r"gallery\.0\.f16 hold .* bytes, .* were written"):
        open_gallery(folder, META["model_fingerprint"], META["ckpt"])
