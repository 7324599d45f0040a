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

The positions r_i come from the scorer's one rule (`geoloc.eval.scoring`): r_i = (i - 1) + the number of
non-relevant, non-junk references scored strictly above the i-th relevant one.

Where this differs from that script:
- ties: the script orders equal scores as np.argsort happens to (unspecified). Here a relevant reference tied with
  irrelevant ones ranks before them, in the query's favour as in `recall_at_k`;
- a query with no relevant reference is silently counted as AP 0 and R@K 0 there; here it raises;
- R@1% uses K = max(1, floor(N / 100)) as all of geoloc's recall (the script prints CMC[round(N / 100)]).
"""
from __future__ import annotations

from typing import Iterable

import torch

from geoloc.data.relevance import JUNK_LABEL, Relevance, label_tensor
from geoloc.eval.descriptors import checked_pair
from geoloc.eval.keys import KeySet
from geoloc.eval.recall import check_ks, recall_summary
from geoloc.eval.scoring import rank

__all__ = ["AP_KEYS", "JUNK_LABEL", "average_precision", "mean_average_precision"]

AP_KEYS = KeySet({"AP": 0.0})


def average_precision(relevant_ranks: torch.Tensor) -> dict[str, float]:
    """{"AP": the mean over queries of the trapezoid AP} of (Q, G) 0-based ranks of each query's relevant
    references, ascending, -1 padding (`scoring.Ranking.relevant_ranks`); a query with no relevant reference
    scores 0 and counts in the mean."""
    valid = relevant_ranks >= 0
    at = relevant_ranks.double().clamp(min=0)  # padding: any rank, masked below
    i = torch.arange(1, relevant_ranks.shape[1] + 1, dtype=torch.float64)[None, :]  # the i-th relevant (1-based)
    precision = i / (at + 1)
    old_precision = torch.where(at > 0, (i - 1) / at.clamp(min=1), torch.ones_like(at))
    terms = torch.where(valid, (old_precision + precision) / 2, torch.zeros_like(at))
    per_query = terms.sum(dim=1) / valid.sum(dim=1).clamp(min=1)
    return AP_KEYS.values({"AP": per_query.mean()})


def mean_average_precision(query, reference, query_labels, reference_labels, ks: Iterable[int] = (1,),
                           chunk_size: int | None = None) -> dict[str, float]:
    """{"R@K" for K in ``ks``, "R@1%", "AP"}: University-1652's label recall and mean AP, Python floats in [0, 1].

    query: Q x D, reference: N x D descriptors (tensors or numpy; normalised and checked as in `recall_at_k`);
    query_labels (Q,), reference_labels (N,) integers, -1 = junk reference. Every query's label must belong to
    some reference, or this raises. One pass of the scorer's stream (``chunk_size`` queries at a time).
    """
    ks = check_ks(ks)
    if chunk_size is not None and int(chunk_size) < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    q, r = checked_pair(query, reference)
    label_tensor(query_labels, "query_labels", q.shape[0])
    label_tensor(reference_labels, "reference_labels", r.shape[0])
    relevance = Relevance.from_labels(query_labels, reference_labels)
    found = rank(q, r, relevance, every_relevant=True, chunk_size=chunk_size)
    return {**recall_summary(found.ranks, ks, r.shape[0]), **average_precision(found.relevant_ranks)}
