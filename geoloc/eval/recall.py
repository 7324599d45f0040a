"""Recall@K for retrieval with one positive per query (SAFA, TransGeo, Sample4Geo), plus VIGOR's hit rate.

Convention (repos disagree; docs/conventions.md "Ranks and Recall@K" and "VIGOR hit rate" fix this one):
- descriptors are L2-normalised and compared by d = 2 - 2 a.b, i.e. ranked by inner product. Rows that are not
  unit length are L2-normalised first (cosine ranking); non-finite or all-zero rows raise
  (geoloc.eval.descriptors), on every backend;
- query i's positive is reference p_i (default p_i = i, the one-to-one CVUSA / CVACT case);
- rank(i) = the number of references other than p_i strictly closer to query i than p_i, so a tie counts in the
  query's favour; semi-positives count as any other reference; R@K = mean(rank < K) (`geoloc.eval.scoring`);
- hit rate (with semi-positives), as the code behind VIGOR's published figures computes it (VIGOR's
  `validate_top`, Sample4Geo's `evaluate/vigor.py`): query i is a hit when no reference outside p_i and its
  semi-positives is strictly closer than p_i. With a semi-positive first, then a negative, then p_i, that is a miss;
- R@1% uses K = max(1, floor(N / 100)) with N the gallery size: 88 at N = 8,884.
"""
from __future__ import annotations

import operator
from typing import Iterable

import torch

from geoloc.data.relevance import Relevance
from geoloc.eval.candidates import rank_candidates
from geoloc.eval.descriptors import checked_pair
from geoloc.eval.search_index import GalleryIndex
from geoloc.eval.keys import KeySet
from geoloc.eval.scoring import check_chunk, rank, relevant_scores

__all__ = ["HIT_RATE_KEYS", "check_ks", "hit_rate", "one_percent_k", "recall_at_k", "recall_keys", "recall_summary"]

HIT_RATE_KEYS = KeySet({"hit_rate": 0.0})


def one_percent_k(n: int) -> int:
    """K of R@1% for a gallery of n references: max(1, floor(n / 100))."""
    return max(1, n // 100)


def check_ks(ks: Iterable[int]) -> tuple[int, ...]:
    """``ks`` as a tuple of positive ints, or a ValueError."""
    try:
        out = tuple(operator.index(k) for k in ks if not isinstance(k, bool))
    except TypeError:
        out = ()
    if not out or min(out) < 1:
        raise ValueError(f"ks must be a non-empty sequence of positive ints, got {ks!r}")
    return out


def recall_keys(ks: Iterable[int]) -> KeySet:
    """R@K for each K in ``ks``, then R@1%."""
    return KeySet({**{f"R@{k}": 0.0 for k in ks}, "R@1%": 0.0})


def recall_summary(ranks: torch.Tensor, ks: Iterable[int], num_references: int) -> dict[str, float]:
    """{"R@K": mean(rank < K) for K in ks, "R@1%": mean(rank < max(1, floor(N / 100)))} of (Q,) ranks."""
    cutoffs = {f"R@{k}": k for k in ks} | {"R@1%": one_percent_k(num_references)}
    return recall_keys(ks).values({key: (ranks < k).double().mean() for key, k in cutoffs.items()})


def hit_rate(hits: torch.Tensor) -> dict[str, float]:
    """{"hit_rate": the share of hits} of (Q,) booleans."""
    return HIT_RATE_KEYS.values({"hit_rate": hits.double().mean()})


def recall_at_k(query, reference, ks: Iterable[int] = (1, 5, 10), backend: str = "torch",
                chunk_size: int | None = None, positives=None, semi_positives=None) -> dict[str, float]:
    """R@K for each K in ``ks`` and R@1%, as Python floats in [0, 1].

    Args:
        query: Q x D descriptors (torch tensor or numpy array). Rows off unit length by more than 1e-3 are
            L2-normalised (cosine); unit rows are used as given. NaN/inf rows raise FloatingPointError, all-zero
            rows ValueError.
        reference: N x D descriptors; without ``positives``, N >= Q and reference[i] is query i's true match
            (extra rows are distractors). Same rules as ``query``.
        ks: the K values; the keys are ``"R@{K}"``, plus ``"R@1%"`` with K = max(1, floor(N / 100)).
        backend: ``"torch"`` (exact, chunked: `geoloc.eval.scoring`) or ``"faiss"`` (a flat inner-product index
            searched for the top max(K, K of R@1%), ranked by `geoloc.eval.candidates`: the same numbers; needs
            the ``faiss-cpu`` extra).
        chunk_size: queries per block (torch backend).
        positives: (Q,) integer index of each query's positive reference (default: query i matches reference i).
            Queries may share a reference.
        semi_positives: (Q, S) integer indices, -1 for none (VIGOR). They count as any other reference in the
            rank; with them the dict also holds ``"hit_rate"``: the share of queries with no reference outside
            the positive and its semi-positives strictly closer than the positive (VIGOR's code).

    Ranks count the references strictly closer than the true match (ties in the query's favour); see the
    module docstring for the convention.
    """
    ks = check_ks(ks)
    if backend not in ("torch", "faiss"):
        raise ValueError(f"backend must be 'torch' or 'faiss', got {backend!r}")
    check_chunk(chunk_size)
    q, r = checked_pair(query, reference, one_to_one=positives is None)
    if q.ndim != 2:
        raise ValueError(f"query must be N x D, got shape {tuple(q.shape)}")
    relevance = Relevance.one_to_one(q.shape[0], r.shape[0]) if positives is None else None
    if positives is not None or semi_positives is not None:
        positives = relevance.relevant[:, 0] if positives is None else positives
        relevance = Relevance.from_positives(positives, r.shape[0], semi_positives, num_queries=q.shape[0])
    hits = semi_positives is not None
    n_ref = r.shape[0]
    if backend == "torch":
        found = rank(q, r, relevance, hits=hits, chunk_size=chunk_size)
    else:
        index = GalleryIndex(r.shape[1], backend="faiss", kind="flat").add(r)
        scores, rows = index.search(q, max(max(ks), one_percent_k(n_ref)))
        found = rank_candidates(scores, rows, relevance, hits=hits, target_scores=relevant_scores(q, r, relevance))
    out = recall_summary(found.ranks, ks, n_ref)
    if hits:
        out.update(hit_rate(found.hits))
    return out
