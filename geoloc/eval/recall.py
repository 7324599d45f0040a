"""Recall@K for retrieval with one positive per query (SAFA, TransGeo, Sample4Geo), plus VIGOR's hit rate.

Convention (repos disagree; this is the one DESIGN.md fixes):
- descriptors are L2-normalised and compared by d = 2 - 2 a.b, i.e. ranked by inner product. Rows that are not
  unit length are L2-normalised first (cosine ranking); non-finite or all-zero rows raise
  (geoloc.eval.descriptors), on every backend;
- query i's positive is reference p_i (default p_i = i, the one-to-one CVUSA / CVACT case);
- rank(i) = the number of references other than p_i strictly closer to query i than p_i, so a tie counts in the
  query's favour; semi-positives count as any other reference; R@K = mean(rank < K);
- hit rate (with semi-positives) = the share of queries whose closest reference is p_i or a semi-positive;
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


def _check_pair(query, reference, one_to_one: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    q, r = as_float_tensor(query, "query"), as_float_tensor(reference, "reference")
    if q.shape[0] == 0 or r.shape[0] == 0:
        raise ValueError(f"empty descriptors: query {tuple(q.shape)}, reference {tuple(r.shape)}")
    if q.shape[1] != r.shape[1]:
        raise ValueError(f"query and reference dimensions differ: {q.shape[1]} vs {r.shape[1]}")
    if one_to_one and r.shape[0] < q.shape[0]:
        raise ValueError(f"reference[i] must match query[i]: got {q.shape[0]} queries and only {r.shape[0]} "
                         "references (pass positives= when queries share references)")
    dtype = torch.promote_types(q.dtype, r.dtype)
    return unit_rows(q.to(r.device, dtype), "query"), unit_rows(r.to(dtype), "reference")


def _check_chunk(chunk_size: int | None) -> int:
    chunk = int(chunk_size or 1024)
    if chunk < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    return chunk


def _index_tensor(x, name: str, shape: tuple[int, ...], n_ref: int, allow_none: bool) -> torch.Tensor:
    """An integer index array of ``shape`` into ``n_ref`` references (-1 = none where ``allow_none``)."""
    t = torch.as_tensor(x)
    if t.is_floating_point() or t.dtype == torch.bool or t.is_complex():
        raise TypeError(f"{name} must hold integer reference indices, got dtype {t.dtype}")
    if tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    t = t.long().cpu()
    low = -1 if allow_none else 0
    bad = (t < low) | (t >= n_ref)
    if bad.any():
        row = int(torch.nonzero(bad)[0][0])
        raise ValueError(f"{name} of query {row} is {t[row].tolist()}: indices must lie in [{low}, {n_ref})")
    return t


def _resolve_positives(positives, semi_positives, n_query: int, n_ref: int):
    pos = torch.arange(n_query) if positives is None else _index_tensor(
        positives, "positives", (n_query,), n_ref, allow_none=False)
    semi = None
    if semi_positives is not None:
        semi_t = torch.as_tensor(semi_positives)
        if semi_t.ndim != 2 or semi_t.shape[0] != n_query:
            raise ValueError(f"semi_positives must be (Q, S) = ({n_query}, S), got {tuple(semi_t.shape)}")
        semi = _index_tensor(semi_t, "semi_positives", tuple(semi_t.shape), n_ref, allow_none=True)
    return pos, semi


def _mark(rows: torch.Tensor, cols: torch.Tensor, r0: int, width: int, out: torch.Tensor) -> None:
    """Set out[row, col - r0] for the (row, col) pairs whose col lies in the block [r0, r0 + width)."""
    inside = (cols >= r0) & (cols < r0 + width)
    out[rows[inside], cols[inside] - r0] = True


def retrieval_ranks(query, reference, chunk_size: int | None = None, positives=None,
                    semi_positives=None) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """rank[i] = #{j != p_i : query[i].reference[j] > query[i].reference[p_i]}, a (Q,) long tensor on the CPU.

    ``positives`` (Q,) gives p_i (default i). Semi-positives count as any other reference in the rank. With
    ``semi_positives`` (Q, S; -1 = none) it returns ``(rank, hit)``: hit[i] is True when no reference outside
    {p_i} and query i's semi-positives is strictly closer than the closest of them (VIGOR's hit rate, with ties
    in the query's favour as for the rank).

    Exact and chunked: at most ``chunk_size`` queries (default 1024) times a block of references sized to
    ~2^25 scores are in memory at once, never a Q x N matrix. Runs where ``reference`` lives (GPU if there).
    """
    chunk = _check_chunk(chunk_size)  # argument errors first, then the descriptors
    q, r = _check_pair(query, reference, one_to_one=positives is None)
    pos_idx, semi_idx = _resolve_positives(positives, semi_positives, q.shape[0], r.shape[0])
    step = _chunk_rows(chunk)
    ranks = torch.empty(q.shape[0], dtype=torch.long)
    hits = torch.empty(q.shape[0], dtype=torch.bool)
    for q0 in range(0, q.shape[0], chunk):
        qc = q[q0:q0 + chunk]
        rows = torch.arange(qc.shape[0], device=r.device)
        p = pos_idx[q0:q0 + qc.shape[0]].to(r.device)
        pos = (qc * r[p]).sum(dim=1, keepdim=True)
        count = torch.zeros(qc.shape[0], dtype=torch.long, device=r.device)
        if semi_idx is not None:
            sp = semi_idx[q0:q0 + qc.shape[0]].to(r.device)
            semi_scores = (qc[:, None, :] * r[sp.clamp(min=0)]).sum(dim=2).masked_fill(sp < 0, float("-inf"))
            best = torch.maximum(pos, semi_scores.max(dim=1, keepdim=True).values)
            beaten = torch.zeros(qc.shape[0], dtype=torch.long, device=r.device)
        for r0 in range(0, r.shape[0], step):
            scores = qc @ r[r0:r0 + step].t()
            # The positive never counts against itself, whatever rounding the two products got.
            own = torch.zeros_like(scores, dtype=torch.bool)
            _mark(rows, p, r0, scores.shape[1], own)
            count += ((scores > pos) & ~own).sum(dim=1)
            if semi_idx is not None:
                for s in range(sp.shape[1]):
                    _mark(rows, sp[:, s], r0, scores.shape[1], own)
                beaten += ((scores > best) & ~own).sum(dim=1)
        ranks[q0:q0 + qc.shape[0]] = count.cpu()
        if semi_idx is not None:
            hits[q0:q0 + qc.shape[0]] = (beaten == 0).cpu()
    return ranks if semi_idx is None else (ranks, hits)


def _ranks_faiss(q: torch.Tensor, r: torch.Tensor, kmax: int, pos_idx: torch.Tensor,
                 semi_idx: torch.Tensor | None = None):
    """Ranks (and hits) from a flat FAISS index, exact below ``kmax`` (a rank >= kmax comes back as kmax)."""
    index = GalleryIndex(r.shape[1], backend="faiss", kind="flat").add(r)
    kmax = min(kmax, r.shape[0])
    ranks = torch.empty(q.shape[0], dtype=torch.long)
    hits = torch.empty(q.shape[0], dtype=torch.bool)
    step = _chunk_rows(kmax)
    for q0 in range(0, q.shape[0], step):
        qc = q[q0:q0 + step]
        p = pos_idx[q0:q0 + qc.shape[0]]
        scores, idx = index.search(qc, kmax)
        own = idx == p[:, None]
        found = own.any(dim=1)
        # The positive's score as FAISS computed it when it was returned; otherwise every returned item is at
        # least as close, and only the strictly closer ones count.
        pos = (qc.float() * r[p].float()).sum(dim=1).cpu()
        pos[found] = scores[own]
        ranks[q0:q0 + qc.shape[0]] = ((scores > pos[:, None]) & ~own).sum(dim=1)
        if semi_idx is not None:
            sp = semi_idx[q0:q0 + qc.shape[0]]
            semi_scores = (qc.float()[:, None, :] * r[sp.clamp(min=0)].float()).sum(dim=2).cpu()
            best = torch.maximum(pos, semi_scores.masked_fill(sp < 0, float("-inf")).max(dim=1).values)
            in_set = own | (idx[:, :, None] == sp[:, None, :]).any(dim=2)
            # results come sorted by score: if anything outside the set beats the best of it, it is returned
            hits[q0:q0 + qc.shape[0]] = ~((scores > best[:, None]) & ~in_set).any(dim=1)
    return ranks if semi_idx is None else (ranks, hits)


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
        backend: ``"torch"`` (exact, chunked) or ``"faiss"`` (flat inner-product index, same numbers; needs the
            ``faiss-cpu`` extra).
        chunk_size: queries per block (torch backend).
        positives: (Q,) integer index of each query's positive reference (default: query i matches reference i).
            Queries may share a reference.
        semi_positives: (Q, S) integer indices, -1 for none (VIGOR). They count as any other reference in the
            rank; with them the dict also holds ``"hit_rate"``: the share of queries whose closest reference is
            the positive or a semi-positive.

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
    q, r = _check_pair(query, reference, one_to_one=positives is None)
    pos_idx, semi_idx = _resolve_positives(positives, semi_positives, q.shape[0], r.shape[0])
    k_pct = one_percent_k(r.shape[0])
    if backend == "torch":
        found = retrieval_ranks(q, r, chunk_size, pos_idx, semi_idx)
    else:
        found = _ranks_faiss(q, r, max(max(ks), k_pct), pos_idx, semi_idx)
    ranks, hits = found if semi_idx is not None else (found, None)
    out = {f"R@{k}": float((ranks < k).double().mean()) for k in ks}
    out["R@1%"] = float((ranks < k_pct).double().mean())
    if hits is not None:
        out["hit_rate"] = float(hits.double().mean())
    return out
