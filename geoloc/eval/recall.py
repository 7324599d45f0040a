"""Recall@K for retrieval with one true match per query (the cross-view protocol of SAFA, TransGeo, Sample4Geo).

Convention (repos disagree; this is the one DESIGN.md fixes):
- descriptors are L2-normalised and compared by d = 2 - 2 a.b, i.e. ranked by inner product. Rows that are not
  unit length are L2-normalised first (cosine ranking); non-finite or all-zero rows raise
  (geoloc.eval.descriptors), on every backend;
- query i's true match is reference i;
- rank(i) = the number of references strictly closer to query i than its true match, so a tie counts in the
  query's favour; R@K = mean(rank < K);
- R@1% uses K = max(1, floor(N / 100)) with N the gallery size: 88 at N = 8,884.
"""
from __future__ import annotations

import operator
from typing import Iterable

import torch

from geoloc.eval.descriptors import unit_rows
from geoloc.eval.gallery import GalleryIndex, _chunk_rows, as_float_tensor

__all__ = ["recall_at_k", "retrieval_ranks", "one_percent_k"]


def one_percent_k(n: int) -> int:
    """K of R@1% for a gallery of n references: max(1, floor(n / 100))."""
    return max(1, n // 100)


def _check_pair(query, reference) -> tuple[torch.Tensor, torch.Tensor]:
    q, r = as_float_tensor(query, "query"), as_float_tensor(reference, "reference")
    if q.shape[0] == 0 or r.shape[0] == 0:
        raise ValueError(f"empty descriptors: query {tuple(q.shape)}, reference {tuple(r.shape)}")
    if q.shape[1] != r.shape[1]:
        raise ValueError(f"query and reference dimensions differ: {q.shape[1]} vs {r.shape[1]}")
    if r.shape[0] < q.shape[0]:
        raise ValueError(f"reference[i] must match query[i]: got {q.shape[0]} queries and only {r.shape[0]} "
                         "references")
    dtype = torch.promote_types(q.dtype, r.dtype)
    return unit_rows(q.to(r.device, dtype), "query"), unit_rows(r.to(dtype), "reference")


def _check_chunk(chunk_size: int | None) -> int:
    chunk = int(chunk_size or 1024)
    if chunk < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    return chunk


def retrieval_ranks(query, reference, chunk_size: int | None = None) -> torch.Tensor:
    """rank[i] = #{j != i : query[i].reference[j] > query[i].reference[i]}, a (Q,) long tensor on the CPU.

    Exact and chunked: at most ``chunk_size`` queries (default 1024) times a block of references sized to
    ~2^25 scores are in memory at once, never a Q x N matrix. Runs where ``reference`` lives (GPU if there).
    """
    chunk = _check_chunk(chunk_size)  # argument errors first, then the descriptors
    q, r = _check_pair(query, reference)
    step = _chunk_rows(chunk)
    ranks = torch.empty(q.shape[0], dtype=torch.long)
    for q0 in range(0, q.shape[0], chunk):
        qc = q[q0:q0 + chunk]
        pos = (qc * r[q0:q0 + qc.shape[0]]).sum(dim=1, keepdim=True)
        rows = torch.arange(qc.shape[0], device=r.device)
        count = torch.zeros(qc.shape[0], dtype=torch.long, device=r.device)
        for r0 in range(0, r.shape[0], step):
            greater = qc @ r[r0:r0 + step].t() > pos
            # The true match never counts against itself, whatever rounding the two products got.
            own = (rows + q0 >= r0) & (rows + q0 < r0 + greater.shape[1])
            greater[rows[own], rows[own] + q0 - r0] = False
            count += greater.sum(dim=1)
        ranks[q0:q0 + qc.shape[0]] = count.cpu()
    return ranks


def _ranks_faiss(q: torch.Tensor, r: torch.Tensor, kmax: int) -> torch.Tensor:
    """Ranks from a flat FAISS index, exact below ``kmax`` (a rank >= kmax comes back as kmax)."""
    index = GalleryIndex(r.shape[1], backend="faiss", kind="flat").add(r)
    kmax = min(kmax, r.shape[0])
    ranks = torch.empty(q.shape[0], dtype=torch.long)
    step = _chunk_rows(kmax)
    for q0 in range(0, q.shape[0], step):
        qc = q[q0:q0 + step]
        scores, idx = index.search(qc, kmax)
        own = idx == torch.arange(q0, q0 + qc.shape[0])[:, None]
        found = own.any(dim=1)
        # The true match's score as FAISS computed it when it was returned; otherwise every returned item is at
        # least as close, and only the strictly closer ones count.
        pos = (qc.float() * r[q0:q0 + qc.shape[0]].float()).sum(dim=1).cpu()
        pos[found] = scores[own]
        ranks[q0:q0 + qc.shape[0]] = (scores > pos[:, None]).sum(dim=1)
    return ranks


def recall_at_k(query, reference, ks: Iterable[int] = (1, 5, 10), backend: str = "torch",
                chunk_size: int | None = None) -> dict[str, float]:
    """R@K for each K in ``ks`` and R@1%, as Python floats in [0, 1].

    Args:
        query: Q x D descriptors (torch tensor or numpy array). Rows off unit length by more than 1e-3 are
            L2-normalised (cosine); unit rows are used as given. NaN/inf rows raise FloatingPointError, all-zero
            rows ValueError.
        reference: N x D descriptors, N >= Q; reference[i] is query i's true match (extra rows are distractors).
            Same rules as ``query``.
        ks: the K values; the keys are ``"R@{K}"``, plus ``"R@1%"`` with K = max(1, floor(N / 100)).
        backend: ``"torch"`` (exact, chunked) or ``"faiss"`` (flat inner-product index, same numbers; needs the
            ``faiss-cpu`` extra).
        chunk_size: queries per block (torch backend).

    Ranks count the references strictly closer than the true match (ties in the query's favour); see the
    module docstring for the convention.
    """
    try:
        ks = tuple(operator.index(k) for k in ks if not isinstance(k, bool))
    except TypeError:
        ks = ()
    if not ks or min(ks) < 1:
        raise ValueError("ks must be a non-empty sequence of positive ints")
    if backend not in ("torch", "faiss"):
        raise ValueError(f"backend must be 'torch' or 'faiss', got {backend!r}")
    _check_chunk(chunk_size)
    q, r = _check_pair(query, reference)
    k_pct = one_percent_k(r.shape[0])
    if backend == "torch":
        ranks = retrieval_ranks(q, r, chunk_size)
    else:
        ranks = _ranks_faiss(q, r, max(max(ks), k_pct))
    out = {f"R@{k}": float((ranks < k).double().mean()) for k in ks}
    out["R@1%"] = float((ranks < k_pct).double().mean())
    return out
