"""Average precision and label recall over a ranked gallery, as University-1652 (Zheng et al., ACM MM 2020) scores.

A reference is relevant to a query when their labels (building ids) are equal; every relevant reference counts,
not only one positive. This follows the benchmark's `evaluate_gpu.py` (layumi/University1652-Baseline,
`compute_mAP`):

- the gallery is ranked by inner product, best first;
- references labelled -1 are junk: left out of the ranking (neither relevant nor in front of anything);
- with G relevant references at 0-based ranks r_1 < ... < r_G, AP = (1/G) sum_i (p_old_i + p_i) / 2, with
  p_i = i / (r_i + 1) the precision at the i-th hit and p_old_i = (i - 1) / r_i the precision just before it
  (1 when r_i = 0): a trapezoid rule over the precision-recall curve, not the plain mean of p_i that
  scikit-learn's average_precision_score gives. One relevant reference at rank 1 scores (0/1 + 1/2) / 2 = 0.25
  here, 0.5 there; a single relevant reference at rank r > 0 scores 1 / (2 (r + 1));
- AP is the mean over queries; R@K is the share of queries with a relevant reference in the top K (the
  benchmark's CMC[K-1]).

Where this differs from that script:
- ties: the script orders equal scores as np.argsort happens to (unspecified). Here a relevant reference tied with
  irrelevant ones ranks before them, in the query's favour as in `recall_at_k`;
- a query with no relevant reference is silently counted as AP 0 and R@K 0 there; here it raises;
- R@1% uses K = max(1, floor(N / 100)) as all of geoloc's recall (the script prints CMC[round(N / 100)]).
"""
from __future__ import annotations

import operator
from typing import Iterable

import torch

from geoloc.eval.recall import _check_pair, one_percent_k

__all__ = ["JUNK_LABEL", "check_ks", "label_tensor", "mean_average_precision"]

JUNK_LABEL = -1
_SORT_BUDGET = 1 << 22  # query x reference elements per block: ~8 such arrays of 8 bytes, about 256 MiB


def check_ks(ks: Iterable[int]) -> tuple[int, ...]:
    """``ks`` as a tuple of positive ints, or a ValueError."""
    try:
        out = tuple(operator.index(k) for k in ks if not isinstance(k, bool))
    except TypeError:
        out = ()
    if not out or min(out) < 1:
        raise ValueError(f"ks must be a non-empty sequence of positive ints, got {ks!r}")
    return out


def label_tensor(x, name: str, rows: int) -> torch.Tensor:
    """``x`` as a (rows,) int64 CPU tensor of labels, or an error naming ``name``."""
    t = torch.as_tensor(x)
    if t.is_floating_point() or t.dtype == torch.bool or t.is_complex():
        raise TypeError(f"{name} must hold integer labels, got dtype {t.dtype}")
    if tuple(t.shape) != (rows,):
        raise ValueError(f"{name} must have shape ({rows},), one label per row of its descriptors, "
                         f"got {tuple(t.shape)}")
    return t.long().cpu()


def _check_every_query_has_a_match(query_labels: torch.Tensor, reference_labels: torch.Tensor) -> None:
    kept = reference_labels[reference_labels != JUNK_LABEL]
    missing = ~torch.isin(query_labels, kept)
    if missing.any():
        i = int(torch.nonzero(missing)[0])
        raise ValueError(
            f"query {i} has label {int(query_labels[i])}, which no reference has (junk references, label "
            f"{JUNK_LABEL}, do not count): average precision is undefined for it ({int(missing.sum())} such "
            "queries). Leave those queries out, or add their places to the gallery.")


def _ranked_relevance(scores: torch.Tensor, relevant: torch.Tensor) -> torch.Tensor:
    """(c, N) bool: relevance in ranked order, best score first; among equal scores, relevant first."""
    # Two stable sorts: relevant first, then by score; the second keeps the first's order within a tie.
    order = torch.sort(relevant.to(torch.int8), dim=1, descending=True, stable=True).indices
    by_score = torch.sort(scores.gather(1, order), dim=1, descending=True, stable=True).indices
    return relevant.gather(1, order.gather(1, by_score))


def mean_average_precision(query, reference, query_labels, reference_labels, ks: Iterable[int] = (1,),
                           chunk_size: int | None = None) -> dict[str, float]:
    """{"AP", "R@K" for K in ``ks``, "R@1%"}: University-1652's mean AP and label recall, Python floats in [0, 1].

    query: Q x D, reference: N x D descriptors (tensors or numpy; normalised and checked as in `recall_at_k`);
    query_labels (Q,), reference_labels (N,) integers, -1 = junk reference. Every query's label must belong to
    some reference, or this raises. Chunked over queries: ``chunk_size`` queries (default: as many as keep a
    block near 4M scores) are ranked against the whole gallery at once; runs where ``reference`` lives.
    """
    ks = check_ks(ks)
    if chunk_size is not None and int(chunk_size) < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    q, r = _check_pair(query, reference, one_to_one=False)
    n_ref = r.shape[0]
    q_labels = label_tensor(query_labels, "query_labels", q.shape[0])
    r_labels = label_tensor(reference_labels, "reference_labels", n_ref)
    _check_every_query_has_a_match(q_labels, r_labels)
    chunk = int(chunk_size) if chunk_size is not None else max(1, _SORT_BUDGET // n_ref)
    cutoffs = {f"R@{k}": k for k in ks} | {"R@1%": one_percent_k(n_ref)}
    found = dict.fromkeys(cutoffs, 0)
    ap = torch.empty(q.shape[0], dtype=torch.float64)  # summed once at the end: the same total for any chunking
    r_labels_dev = r_labels.to(r.device)
    junk = r_labels_dev == JUNK_LABEL
    for q0 in range(0, q.shape[0], chunk):
        qc = q[q0:q0 + chunk]
        relevant = q_labels[q0:q0 + qc.shape[0]].to(r.device)[:, None] == r_labels_dev[None, :]
        # Junk goes below every real score; every relevant reference ranks above it, so its place is as if removed.
        scores = (qc @ r.t()).masked_fill(junk[None, :], float("-inf"))
        ranked = _ranked_relevance(scores, relevant)
        hits = ranked.cumsum(dim=1)  # hits[:, j] = relevant references in the top j + 1
        rows, rank = torch.nonzero(ranked, as_tuple=True)
        # One entry per relevant reference from here on: small, so float64 on the CPU (any accelerator works).
        i = hits[rows, rank].cpu().double()  # this is the i-th relevant reference (1-based) ...
        at = rank.cpu().double()  # ... at 0-based rank r_i
        precision = i / (at + 1)
        old_precision = torch.where(at > 0, (i - 1) / at.clamp(min=1), torch.ones_like(at))
        per_query = torch.zeros(qc.shape[0], dtype=torch.float64)
        per_query.index_add_(0, rows.cpu(), (old_precision + precision) / 2)
        ap[q0:q0 + qc.shape[0]] = per_query / hits[:, -1].cpu().double()
        for key, k in cutoffs.items():
            found[key] += int((hits[:, min(k, n_ref) - 1] > 0).sum())
    out = {"AP": float(ap.mean())}
    out.update({key: found[key] / q.shape[0] for key in cutoffs})
    return out
