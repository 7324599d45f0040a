"""Ranks through the scorer with the argument style of the metric tests, and the one-to-one ranking as it was
computed before the scorer existed (the reference the default run's figures are held to)."""

from __future__ import annotations

import torch

from geoloc.data.relevance import Relevance
from geoloc.eval.descriptors import checked_pair
from geoloc.eval.scoring import rank


def ranks_of(query, reference, positives=None, semi_positives=None, chunk_size=None):
    """(Q,) ranks by the scorer's rule; with semi_positives, (ranks, hits) (VIGOR's hit)."""
    q, r = checked_pair(query, reference, one_to_one=positives is None)
    if positives is None and semi_positives is None:
        relevance = Relevance.one_to_one(q.shape[0], r.shape[0])
    else:
        positives = torch.arange(q.shape[0]) if positives is None else positives
        relevance = Relevance.from_positives(positives, r.shape[0], semi_positives)
    found = rank(q, r, relevance, hits=semi_positives is not None, chunk_size=chunk_size)
    return found.ranks if semi_positives is None else (found.ranks, found.hits)


def one_to_one_ranks_before(query, reference, chunk: int = 1024, budget: int = 1 << 25) -> torch.Tensor:
    """One-to-one ranks exactly as geoloc computed them before the scorer: query chunks of ``chunk`` against
    reference blocks of budget // chunk rows, the block products q @ r_block.T compared with the row-wise product
    sum(q_i * r_i) of the positive, which never counts against itself."""
    q, r = checked_pair(query, reference)
    step = max(1, budget // chunk)
    ranks = torch.empty(q.shape[0], dtype=torch.long)
    for q0 in range(0, q.shape[0], chunk):
        qc = q[q0:q0 + chunk]
        rows = torch.arange(qc.shape[0])
        p = torch.arange(q0, q0 + qc.shape[0])
        pos = (qc * r[p]).sum(dim=1, keepdim=True)
        count = torch.zeros(qc.shape[0], dtype=torch.long)
        for r0 in range(0, r.shape[0], step):
            scores = qc @ r[r0:r0 + step].t()
            own = torch.zeros_like(scores, dtype=torch.bool)
            inside = (p >= r0) & (p < r0 + scores.shape[1])
            own[rows[inside], p[inside] - r0] = True
            count += ((scores > pos) & ~own).sum(dim=1)
        ranks[q0:q0 + qc.shape[0]] = count
    return ranks
