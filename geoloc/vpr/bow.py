"""Bag of binary words over ORB descriptors (MMDIP's image code), tf-idf weighted and L2-normalised.

Vocabulary choice: binary k-majority with Hamming assignment (the flat, one-level form of DBoW2's vocabulary),
not k-means on float-cast bytes as the authors' code does. A float mean of packed ORB bytes is not a descriptor
(each byte packs 8 independent tests), while a per-bit majority is the Hamming-space centroid, so words stay
valid ORB descriptors. Hamming distances are computed as |a| + |c| - 2 a.c on unpacked bits with one matrix
product, which is fast enough for a per-query coding budget of a few ms.

tf-idf: tf_w = n_w(image) / n(image); idf_w = ln(N / N_w), with N the vocabulary's training images and N_w those
containing word w (at least 1). An image without keypoints (blank) codes to the zero vector, never NaN.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy import sparse

DESC_BYTES = 32


class ORBExtractor:
    """ORB keypoints + 256-bit descriptors of an RGB or gray uint8 image; (n, 32) uint8, n may be 0."""

    def __init__(self, nfeatures: int = 500, patch_size: int = 31, fast_threshold: int = 20):
        self.orb = cv2.ORB_create(nfeatures=nfeatures, edgeThreshold=patch_size, patchSize=patch_size,
                                  fastThreshold=fast_threshold)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        if image.dtype != np.uint8:
            raise ValueError(f"ORB needs a uint8 image, got {image.dtype}")
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        _, desc = self.orb.detectAndCompute(gray, None)
        return np.zeros((0, DESC_BYTES), np.uint8) if desc is None else desc


def unpack_bits(desc: np.ndarray) -> np.ndarray:
    """(n, 32) uint8 -> (n, 256) float32 of 0/1."""
    return np.unpackbits(desc, axis=1).astype(np.float32)


def _nearest(bits: np.ndarray, word_bits: np.ndarray, chunk: int = 8192) -> np.ndarray:
    """Index of the Hamming-nearest word of each row of `bits`."""
    word_norm = word_bits.sum(1)
    out = np.empty(len(bits), np.int64)
    for s in range(0, len(bits), chunk):  # chunks bound the n x K distance matrix
        b = bits[s : s + chunk]
        dist = word_norm[None, :] - 2.0 * (b @ word_bits.T)  # + |b| is constant per row
        out[s : s + chunk] = dist.argmin(1)
    return out


class Vocabulary:
    """K binary words (K x 32 uint8) and their idf weights."""

    def __init__(self, words: np.ndarray, idf: np.ndarray):
        self.words = np.ascontiguousarray(words, dtype=np.uint8)
        self.idf = np.asarray(idf, dtype=np.float32)
        self._word_bits = unpack_bits(self.words)

    @property
    def size(self) -> int:
        return len(self.words)

    @classmethod
    def fit(cls, descriptors: list[np.ndarray], size: int = 1000, iters: int = 10, seed: int = 0,
            max_descriptors: int = 200_000) -> "Vocabulary":
        """k-majority clustering of the descriptors of training images (one array per image)."""
        rng = np.random.default_rng(seed)
        all_desc = np.concatenate([d for d in descriptors if len(d)] or [np.zeros((0, DESC_BYTES), np.uint8)])
        if len(all_desc) == 0:
            raise ValueError("no ORB descriptors in the vocabulary's training images")
        if len(all_desc) > max_descriptors:
            all_desc = all_desc[rng.choice(len(all_desc), max_descriptors, replace=False)]
        bits = unpack_bits(all_desc)
        k = min(size, len(np.unique(all_desc, axis=0)))
        words = bits[rng.choice(len(bits), k, replace=False)]
        for _ in range(iters):
            assign = _nearest(bits, words)
            sizes = np.bincount(assign, minlength=k)
            members = sparse.csr_matrix((np.ones(len(bits), np.float32), (assign, np.arange(len(bits)))),
                                        shape=(k, len(bits)))
            sums = members @ bits  # per-word count of set bits
            new = (2 * sums > sizes[:, None]).astype(np.float32)  # per-bit majority
            empty = sizes == 0
            new[empty] = bits[rng.choice(len(bits), int(empty.sum()), replace=False)]
            if np.array_equal(new, words):
                break
            words = new
        words = np.packbits(words.astype(np.uint8), axis=1)
        vocab = cls(words, np.ones(k, np.float32))
        doc_freq = np.zeros(k)
        for d in descriptors:
            if len(d):
                doc_freq[np.unique(vocab.assign(d))] += 1
        vocab.idf = np.log(len(descriptors) / np.maximum(doc_freq, 1)).astype(np.float32)
        return vocab

    def assign(self, desc: np.ndarray) -> np.ndarray:
        return _nearest(unpack_bits(desc), self._word_bits)

    def encode(self, desc: np.ndarray) -> np.ndarray:
        """tf-idf BoW vector (K float32), L2-normalised; zeros when there are no descriptors."""
        vec = np.zeros(self.size, np.float32)
        if len(desc) == 0:
            return vec
        vec += np.bincount(self.assign(desc), minlength=self.size) / len(desc)
        vec *= self.idf
        norm = np.linalg.norm(vec)
        return vec / norm if norm > 0 else vec

    def save(self, path: str | Path) -> None:
        np.savez(path, words=self.words, idf=self.idf)

    @classmethod
    def load(cls, path: str | Path) -> "Vocabulary":
        with np.load(path) as f:
            return cls(f["words"], f["idf"])
