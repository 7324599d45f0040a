import numpy as np
import pytest
from geoloc.vpr import (
    Gallery,
    ORBExtractor,
    Vocabulary,
    fused_descriptors,
    fused_similarity,
)
from geoloc.vpr.bow import _nearest, unpack_bits


def noisy_copies(rng, base, n, flips=6):
    bits = np.unpackbits(np.repeat(base[None], n, 0), axis=1)
    for row in bits:
        row[rng.choice(256, flips, replace=False)] ^= 1
    return np.packbits(bits, axis=1)


def test_hamming_assignment_matches_popcount():
    rng = np.random.default_rng(0)
    desc, words = rng.integers(0, 256, (40, 32), dtype=np.uint8), rng.integers(0, 256, (7, 32), dtype=np.uint8)
    popcount = np.unpackbits(desc[:, None, :] ^ words[None, :, :], axis=2).sum(2)
    got = _nearest(unpack_bits(desc), unpack_bits(words))
    assert np.array_equal(popcount[np.arange(40), got], popcount.min(1))


def test_k_majority_recovers_cluster_centres_and_idf():
    rng = np.random.default_rng(1)
    bases = rng.integers(0, 256, (3, 32), dtype=np.uint8)
    # image 0 and 1 hold words 0 and 1; every image holds word 2
    images = [np.concatenate([noisy_copies(rng, bases[i % 2], 30), noisy_copies(rng, bases[2], 30)]) for i in range(4)]
    vocab = Vocabulary.fit(images, size=3, seed=0)
    order = [int(np.flatnonzero((vocab.words == b).all(1))[0]) for b in bases]  # each base is a word, exactly
    assert vocab.idf[order[2]] == pytest.approx(0.0)
    assert vocab.idf[order[0]] == pytest.approx(np.log(2))


def test_bow_encode_is_unit_or_zero_and_roundtrips(tmp_path):
    rng = np.random.default_rng(2)
    bases = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    images = [noisy_copies(rng, bases[i], 20) for i in range(5)]
    vocab = Vocabulary.fit(images, size=5, seed=0)
    v = vocab.encode(images[0])
    assert v.shape == (5,) and np.linalg.norm(v) == pytest.approx(1.0)
    empty = vocab.encode(np.zeros((0, 32), np.uint8))
    assert not empty.any() and not np.isnan(empty).any()
    vocab.save(tmp_path / "vocab.npz")
    again = Vocabulary.load(tmp_path / "vocab.npz")
    assert np.array_equal(again.encode(images[1]), vocab.encode(images[1]))


def test_orb_on_blank_image_gives_no_descriptors():
    orb = ORBExtractor()
    assert orb(np.zeros((128, 128, 3), np.uint8)).shape == (0, 32)
    rng = np.random.default_rng(0)
    textured = (rng.random((128, 128)) * 255).astype(np.uint8)
    d = orb(textured)
    assert d.ndim == 2 and d.shape[1] == 32 and len(d) > 0
    with pytest.raises(ValueError, match="uint8"):
        orb(textured.astype(np.float32))


def test_fused_descriptors_reproduce_eq5_with_zero_codes():
    rng = np.random.default_rng(3)
    qb, qs = rng.random((4, 10)), rng.random((4, 6))
    rb, rs = rng.random((5, 10)), rng.random((5, 6))
    qb[1] = 0  # a blank query image
    rb[2] = 0  # a blank reference image
    want = fused_similarity(qb, qs, rb, rs, 0.5)
    assert want[1, 0] == pytest.approx(0.5 * (qs[1] @ rs[0]) / np.linalg.norm(qs[1]) / np.linalg.norm(rs[0]))
    q, r = fused_descriptors(qb, qs, 0.5, "query"), fused_descriptors(rb, rs, 0.5, "reference")
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1, atol=1e-6)
    np.testing.assert_allclose(q @ r.T, want, atol=1e-6)
    assert not np.isnan(q).any()


def test_gallery_roundtrip_and_search(tmp_path):
    rng = np.random.default_rng(4)
    bow, spm = rng.random((6, 8)), rng.random((6, 5))
    g = Gallery(bow, spm, np.arange(10, 16), levels=1)
    g.save(tmp_path / "gallery.npz")
    g2 = Gallery.load(tmp_path / "gallery.npz")
    assert g2.levels == 1
    assert np.array_equal(g2.search(bow, spm, k=1)[:, 0], np.arange(10, 16))
