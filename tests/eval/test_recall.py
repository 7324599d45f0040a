"""recall_at_k and GalleryIndex against brute force (docs/conventions.md "Ranks and Recall@K")."""
import numpy as np
import pytest
import torch
from geoloc.eval import GalleryIndex, recall_at_k
from geoloc.eval import scoring
from geoloc.eval.recall import one_percent_k

from helpers.ranking import ranks_of

try:
    import faiss  # noqa: F401
    HAVE_FAISS = True
except ImportError:
    HAVE_FAISS = False
needs_faiss = pytest.mark.skipif(not HAVE_FAISS, reason="faiss-cpu not installed")


def descriptors(q, n, d, noise, seed=0):
    """q queries and n >= q references (reference i matches query i), unit rows, float32 numpy."""
    rng = np.random.default_rng(seed)
    ref = rng.standard_normal((n, d)).astype(np.float32)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    query = ref[:q] + noise * rng.standard_normal((q, d)).astype(np.float32)
    query /= np.linalg.norm(query, axis=1, keepdims=True)
    return query, ref


def brute_ranks(query, ref):
    """One query at a time, by squared distance: references strictly closer than the true match."""
    ranks = []
    for i, qi in enumerate(query.astype(np.float64)):
        dist = ((ref.astype(np.float64) - qi) ** 2).sum(axis=1)
        closer = dist < dist[i]
        closer[i] = False
        ranks.append(int(closer.sum()))
    return np.array(ranks)


def brute_recall(ranks, n, ks):
    out = {f"R@{k}": float(np.mean(ranks < k)) for k in ks}
    out["R@1%"] = float(np.mean(ranks < max(1, n // 100)))
    return out


@pytest.mark.parametrize("q,n", [(300, 300), (120, 400)])
def test_matches_brute_force(q, n):
    query, ref = descriptors(q, n, 16, noise=0.4)
    ranks = brute_ranks(query, ref)
    assert 0.05 < np.mean(ranks == 0) < 0.95  # a spread of ranks, so the test can fail
    ks = (1, 2, 5, 10, 50)
    got = recall_at_k(query, ref, ks=ks)
    assert got == pytest.approx(brute_recall(ranks, n, ks), abs=0)
    assert all(isinstance(v, float) for v in got.values())
    assert set(got) == {"R@1", "R@2", "R@5", "R@10", "R@50", "R@1%"}
    got_ranks = ranks_of(query, ref)
    assert got_ranks.dtype == torch.long
    np.testing.assert_array_equal(got_ranks.numpy(), ranks)


def test_default_keys_and_tensor_input():
    query, ref = descriptors(40, 40, 8, noise=0.5)
    got = recall_at_k(torch.from_numpy(query), torch.from_numpy(ref))
    assert list(got) == ["R@1", "R@5", "R@10", "R@1%"]
    assert got == recall_at_k(query, ref)
    assert all(0.0 <= v <= 1.0 for v in got.values())


TIE_REF = np.array([[1, 0, 0, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0.5, 0.5, 0.5, 0.5]], np.float32)
TIE_QUERY = np.array([[1, 0, 0, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], np.float32)


def test_ties_count_in_the_querys_favour():
    # Exactly representable vectors, so ties are exact. Queries 0 and 1 tie with each other's match (score 1
    # both): rank 0. Query 2: match 1, reference 3 scores .5: rank 0. Query 3: match .5, the rest 0: rank 0.
    np.testing.assert_array_equal(ranks_of(TIE_QUERY, TIE_REF).numpy(), [0, 0, 0, 0])
    query = TIE_QUERY.copy()
    query[2] = [1, 0, 0, 0]  # its match now scores 0; references 0, 1 (score 1) and 3 (.5) are closer: rank 3
    np.testing.assert_array_equal(ranks_of(query, TIE_REF).numpy(), [0, 0, 3, 0])
    assert recall_at_k(query, TIE_REF, ks=(1, 3, 4)) == {"R@1": 0.75, "R@3": 0.75, "R@4": 1.0, "R@1%": 0.75}


def test_one_percent_k_rule():
    assert one_percent_k(8884) == 88
    assert one_percent_k(50) == 1
    assert one_percent_k(99) == 1 and one_percent_k(100) == 1 and one_percent_k(250) == 2


def test_one_percent_at_cvusa_size():
    n = 8884
    query, ref = descriptors(n, n, 4, noise=0.2, seed=3)
    got = recall_at_k(query, ref, ks=(1,))
    ranks = np.empty(n, int)  # brute force, in float64, a block of rows at a time
    for s in range(0, n, 2000):
        sim = query[s:s + 2000].astype(np.float64) @ ref.astype(np.float64).T
        pos = sim[np.arange(sim.shape[0]), np.arange(s, s + sim.shape[0])]
        ranks[s:s + 2000] = (sim > pos[:, None]).sum(axis=1)
    hits = {k: int((ranks < k).sum()) for k in (87, 88, 89)}
    assert hits[88] - hits[87] > 10 and hits[89] - hits[88] > 10  # K = 87 or 89 would be caught
    assert abs(got["R@1%"] * n - hits[88]) <= 2  # float32 against float64 near-ties
    assert abs(got["R@1"] * n - (ranks == 0).sum()) <= 2


@pytest.mark.parametrize("chunk_size", [1, 7, 64, 10_000])
def test_chunking_invariance(chunk_size):
    query, ref = descriptors(150, 200, 12, noise=0.4, seed=1)
    expected = ranks_of(query, ref, chunk_size=1024)
    torch.testing.assert_close(ranks_of(query, ref, chunk_size=chunk_size), expected)
    assert recall_at_k(query, ref, chunk_size=chunk_size) == recall_at_k(query, ref)


def test_reference_blocks_are_bounded(monkeypatch):
    # Force tiny reference blocks: the result must not depend on how the gallery is split.
    query, ref = descriptors(60, 90, 8, noise=0.4, seed=2)
    expected = ranks_of(query, ref)
    monkeypatch.setattr(scoring, "SCORE_BUDGET", 35)  # 5 queries x 7 references
    torch.testing.assert_close(ranks_of(query, ref, chunk_size=5), expected)


@needs_faiss
@pytest.mark.parametrize("q,n", [(300, 300), (100, 350)])
def test_faiss_flat_equals_torch(q, n):
    query, ref = descriptors(q, n, 16, noise=0.4, seed=4)
    ks = (1, 5, 10, 20)
    assert recall_at_k(query, ref, ks=ks, backend="faiss") == recall_at_k(query, ref, ks=ks)


@needs_faiss
def test_faiss_handles_ties_like_torch():
    query = TIE_QUERY.copy()
    query[2] = [1, 0, 0, 0]
    for q in (TIE_QUERY, query):
        assert recall_at_k(q, TIE_REF, ks=(1, 3, 4), backend="faiss") == recall_at_k(q, TIE_REF, ks=(1, 3, 4))


# ---- GalleryIndex ----------------------------------------------------------------------------------------------
def brute_topk(query, ref, k):
    sim = query.astype(np.float64) @ ref.astype(np.float64).T
    idx = np.argsort(-sim, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(sim, idx, axis=1), idx


@pytest.mark.parametrize("backend", ["torch", pytest.param("faiss", marks=needs_faiss)])
def test_gallery_flat_search_matches_brute_force(backend):
    query, ref = descriptors(30, 120, 16, noise=0.5, seed=5)
    index = GalleryIndex(16, backend=backend, chunk_size=7)
    index.add(ref[:50]).add(ref[50:])  # row numbers continue across adds
    assert len(index) == 120
    scores, idx = index.search(query, 5)
    ref_scores, ref_idx = brute_topk(query, ref, 5)
    np.testing.assert_array_equal(idx.numpy(), ref_idx)
    np.testing.assert_allclose(scores.numpy(), ref_scores, atol=1e-5)
    assert index.search(query, 500)[1].shape == (30, 120)  # k capped at the gallery size


def test_gallery_torch_blocks_merge(monkeypatch):
    query, ref = descriptors(20, 100, 8, noise=0.5, seed=6)
    monkeypatch.setattr(scoring, "SCORE_BUDGET", 27)  # 3 queries x 9 references
    _, idx = GalleryIndex(8, chunk_size=3).add(ref).search(query, 12)
    np.testing.assert_array_equal(idx.numpy(), brute_topk(query, ref, 12)[1])


@pytest.mark.parametrize("backend,kind", [
    ("torch", "flat"),
    pytest.param("faiss", "flat", marks=needs_faiss),
    pytest.param("faiss", "ivfpq", marks=needs_faiss),
])
def test_gallery_save_load_round_trip(tmp_path, backend, kind):
    query, ref = descriptors(20, 1000, 16, noise=0.3, seed=7)
    index = GalleryIndex(16, backend=backend, kind=kind, nlist=4, m=4, nbits=4, nprobe=2).add(ref)
    before = index.search(query, 10)
    index.save(tmp_path / "gallery.pt")
    loaded = GalleryIndex.load(tmp_path / "gallery.pt")
    assert (loaded.backend, loaded.kind, len(loaded), loaded.params) == (backend, kind, 1000, index.params)
    after = loaded.search(query, 10)
    torch.testing.assert_close(after[1], before[1])
    torch.testing.assert_close(after[0], before[0])


@needs_faiss
def test_ivfpq_finds_most_matches():
    query, ref = descriptors(200, 5000, 32, noise=0.1, seed=8)
    index = GalleryIndex(32, backend="faiss", kind="ivfpq", nlist=16, m=8, nbits=6, nprobe=16).add(ref)
    _, idx = index.search(query, 10)
    hits = (idx.numpy() == np.arange(200)[:, None]).any(axis=1).mean()
    assert hits > 0.9


def test_load_rejects_other_files(tmp_path):
    torch.save({"something": 1}, tmp_path / "x.pt")
    with pytest.raises(ValueError, match="not a geoloc gallery"):
        GalleryIndex.load(tmp_path / "x.pt")


def test_gallery_bad_inputs():
    with pytest.raises(ValueError, match="backend"):
        GalleryIndex(8, backend="annoy")
    with pytest.raises(ValueError, match="kind"):
        GalleryIndex(8, backend="torch", kind="ivfpq")
    index = GalleryIndex(8)
    with pytest.raises(ValueError, match="empty gallery"):
        index.search(np.zeros((2, 8), np.float32), 1)
    with pytest.raises(ValueError, match="dimension 8"):
        index.add(np.zeros((2, 4), np.float32))
    with pytest.raises(ValueError, match="k must be"):
        index.add(np.ones((2, 8), np.float32)).search(np.ones((1, 8), np.float32), 0)


def test_missing_faiss_gives_install_hint(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_faiss(name, *args, **kwargs):
        if name == "faiss":
            raise ImportError("No module named 'faiss'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_faiss)
    query, ref = descriptors(5, 5, 4, noise=0.1)
    with pytest.raises(ImportError, match="faiss-cpu"):
        recall_at_k(query, ref, backend="faiss")


# ---- bad inputs ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("query,ref,kwargs,err,match", [
    (np.zeros((3, 4)), np.zeros((3, 5)), {}, ValueError, "dimensions differ"),
    (np.zeros((4, 4)), np.zeros((3, 4)), {}, ValueError, "only 3 references"),
    (np.zeros((0, 4)), np.zeros((3, 4)), {}, ValueError, "empty"),
    (np.zeros((3, 4)), np.zeros((0, 4)), {}, ValueError, "empty"),
    (np.zeros(4), np.zeros(4), {}, ValueError, "N x D"),
    ([[1.0]], [[1.0]], {}, TypeError, "numpy array"),
    (np.zeros((3, 4)), np.zeros((3, 4)), {"ks": ()}, ValueError, "ks"),
    (np.zeros((3, 4)), np.zeros((3, 4)), {"ks": (0, 1)}, ValueError, "ks"),
    (np.zeros((3, 4)), np.zeros((3, 4)), {"ks": ("1",)}, ValueError, "ks"),
    (np.zeros((3, 4)), np.zeros((3, 4)), {"backend": "annoy"}, ValueError, "backend"),
    (np.zeros((3, 4)), np.zeros((3, 4)), {"chunk_size": -1}, ValueError, "chunk_size"),
])
def test_bad_inputs(query, ref, kwargs, err, match):
    with pytest.raises(err, match=match):
        recall_at_k(query, ref, **kwargs)


@pytest.mark.parametrize("query_first", [True, False])
def test_mixed_precision_is_ranked_in_the_wider_type(query_first):
    query, ref = descriptors(50, 70, 8, noise=0.4, seed=12)
    wide, narrow = (query.astype(np.float64), ref) if query_first else (query, ref.astype(np.float64))
    expected = recall_at_k(query.astype(np.float64), ref.astype(np.float64), ks=(1, 5))
    assert recall_at_k(wide, narrow, ks=(1, 5)) == expected


def test_bad_inputs_name_the_argument():
    with pytest.raises(TypeError, match="query must be a torch tensor or a numpy array"):
        recall_at_k([[1.0]], np.zeros((1, 1)))
    with pytest.raises(ValueError, match=r"reference must be N x D, got shape \(4,\)"):
        recall_at_k(np.zeros((1, 4)), np.zeros(4))
    with pytest.raises(ValueError, match="got 4 queries and only 3 references"):
        recall_at_k(np.zeros((4, 5)), np.zeros((3, 5)))
    unit = np.eye(3, dtype=np.float32)
    with pytest.raises(ValueError, match="of 3 query descriptors are all zeros"):
        recall_at_k(unit * [[1], [0], [1]], unit)
    with pytest.raises(ValueError, match="of 3 reference descriptors are all zeros"):
        recall_at_k(unit, unit * [[1], [0], [1]])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_tensors_give_the_cpu_numbers():
    query, ref = descriptors(200, 300, 16, noise=0.4, seed=9)
    q, r = torch.from_numpy(query).cuda(), torch.from_numpy(ref).cuda()
    assert recall_at_k(q, r, ks=(1, 5, 10, 50)) == recall_at_k(query, ref, ks=(1, 5, 10, 50))
    _, idx = GalleryIndex(16).add(r).search(q, 5)
    np.testing.assert_array_equal(idx.numpy(), brute_topk(query, ref, 5)[1])


@needs_faiss
def test_faiss_add_in_blocks_keeps_row_numbers(monkeypatch):
    import geoloc.eval.search_index as gallery_mod

    monkeypatch.setattr(gallery_mod, "_ADD_BLOCK", 7)
    query, ref = descriptors(10, 50, 8, noise=0.3, seed=10)
    _, idx = GalleryIndex(8, backend="faiss").add(ref).search(query, 5)
    np.testing.assert_array_equal(idx.numpy(), brute_topk(query, ref, 5)[1])
