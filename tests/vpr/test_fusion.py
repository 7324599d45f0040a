"""MMDIP eq. 5 fusion, M = alpha cos(BoW) + (1 - alpha) cos(SPM), against a hand-written version, at an alpha
other than 0.5 so that the two weights cannot be swapped unnoticed; and the gallery search built on it."""
import warnings

import numpy as np
import pytest
from geoloc.vpr import Gallery, fused_descriptors, fused_similarity
from geoloc.vpr.fusion import l2_normalize


def eq5_by_hand(q_bow, q_spm, r_bow, r_spm, alpha):
    """One (query, reference) pair at a time; a zero code has cosine 0 with everything."""
    def cos(a, b):
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        return 0.0 if na == 0 or nb == 0 else float(a @ b) / (na * nb)

    return np.array([[alpha * cos(qb, rb) + (1 - alpha) * cos(qs, rs) for rb, rs in zip(r_bow, r_spm)]
                     for qb, qs in zip(q_bow, q_spm)])


def codes(seed, n, zero_bow=None, zero_spm=None):
    rng = np.random.default_rng(seed)
    bow, spm = rng.random((n, 10)), rng.random((n, 6))
    if zero_bow is not None:
        bow[zero_bow] = 0  # no ORB keypoint
    if zero_spm is not None:
        spm[zero_spm] = 0
    return bow, spm


@pytest.mark.parametrize("alpha", [0.0, 0.3, 1.0])
def test_fused_descriptors_give_eq5_at_any_alpha(alpha):
    (qb, qs), (rb, rs) = codes(0, 4, zero_bow=1, zero_spm=2), codes(1, 5, zero_bow=3, zero_spm=0)
    want = eq5_by_hand(qb, qs, rb, rs, alpha)
    np.testing.assert_allclose(fused_similarity(qb, qs, rb, rs, alpha), want, atol=1e-6)
    q, r = fused_descriptors(qb, qs, alpha, "query"), fused_descriptors(rb, rs, alpha, "reference")
    assert q.shape == (4, 10 + 6 + 2) and r.shape == (5, 18)
    np.testing.assert_allclose(q @ r.T, want, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-6)  # unit rows, zero codes included
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1, atol=1e-6)


def test_default_alpha_is_the_papers_half():
    (qb, qs), (rb, rs) = codes(2, 3), codes(3, 4)
    np.testing.assert_array_equal(fused_similarity(qb, qs, rb, rs), fused_similarity(qb, qs, rb, rs, 0.5))


def test_l2_normalize_scales_short_and_long_rows_and_keeps_zero_rows():
    x = np.array([[0.3, 0.4], [3.0, 4.0], [0.0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy warns when a masked divide may leave memory uninitialised
        np.testing.assert_allclose(l2_normalize(x), [[0.6, 0.8], [0.6, 0.8], [0.0, 0.0]], rtol=1e-6)


def test_bad_role_and_alpha_are_refused():
    bow, spm = codes(4, 2)
    with pytest.raises(ValueError, match="role must be 'query' or 'reference', got 'gallery'"):
        fused_descriptors(bow, spm, 0.5, "gallery")
    for alpha in (-0.1, 1.5):
        with pytest.raises(ValueError, match=f"alpha must lie in \\[0, 1\\], got {alpha}"):
            fused_descriptors(bow, spm, alpha, "query")


def test_gallery_search_ranks_by_eq5_with_its_alpha():
    # Reference 0 agrees with the query on BoW only, reference 1 on SPM only: alpha decides which comes first.
    bow = np.array([[1.0, 0, 0], [0, 1.0, 0]] + [[0, 0, 1.0]] * 10)
    spm = np.array([[0, 1.0], [1.0, 0]] + [[0, 1.0]] * 10)
    gallery = Gallery(bow, spm, np.arange(100, 112), levels=1)
    q_bow, q_spm = np.array([[1.0, 0, 0]]), np.array([[1.0, 0]])
    assert gallery.search(q_bow, q_spm, alpha=0.8, k=1).tolist() == [[100]]
    assert gallery.search(q_bow, q_spm, alpha=0.2, k=1).tolist() == [[101]]
    assert gallery.search(q_bow, q_spm).shape == (1, 10)  # k = 10 by default
    np.testing.assert_array_equal(gallery.search(q_bow, q_spm, k=12), gallery.search(q_bow, q_spm, 0.5, k=12))


def test_gallery_save_load_round_trip(tmp_path):
    bow, spm = codes(6, 5)
    Gallery(bow, spm, np.arange(20, 25), levels=2).save(tmp_path / "gallery.npz")
    loaded = Gallery.load(tmp_path / "gallery.npz")
    np.testing.assert_array_equal(loaded.bow, bow)
    np.testing.assert_array_equal(loaded.spm, spm)
    np.testing.assert_array_equal(loaded.places, np.arange(20, 25))
    assert loaded.levels == 2 and isinstance(loaded.levels, int)


def test_gallery_search_breaks_ties_by_gallery_order():
    # Three kinds of reference, so the similarities tie in large groups; Python's sort is stable.
    kind = np.random.default_rng(5).integers(0, 3, size=64)
    onehot = np.eye(3)[kind]
    places = np.arange(1000, 1064)
    top = Gallery(onehot, onehot, places, levels=0).search(np.eye(3)[:1], np.eye(3)[:1], k=64)
    sim = eq5_by_hand(np.eye(3)[:1], np.eye(3)[:1], onehot, onehot, 0.5)[0]
    np.testing.assert_array_equal(top[0], places[sorted(range(64), key=lambda j: -sim[j])])
