"""Brute-force references of the losses: plain loops over triplets, for the formula tests."""

from __future__ import annotations

import torch


def brute_hardest(query, reference, ids):
    out = []
    for i in range(len(query)):
        best, best_d = None, float("inf")
        for j in range(len(reference)):
            if j == i or ids[j] == ids[i]:
                continue
            d = ((query[i] - reference[j]) ** 2).sum().item()
            if d < best_d:
                best, best_d = j, d
        if best is not None:
            out.append(best)
    return out


def brute_force(query, reference, alpha=10.0, extra=None, mask=None):
    """One Python term per triplet, written straight from the definition."""
    def d(a, b):
        return ((a - b) ** 2).sum()

    terms = []
    b = len(query)
    for i in range(b):
        for j in range(b):
            if i == j:
                continue
            terms.append(torch.log1p(torch.exp(alpha * (d(query[i], reference[i]) - d(query[i], reference[j])))))
            terms.append(torch.log1p(torch.exp(alpha * (d(reference[i], query[i]) - d(reference[i], query[j])))))
        if extra is not None:
            for k in range(len(extra)):
                if mask is None or mask[i, k]:
                    terms.append(torch.log1p(torch.exp(alpha * (d(query[i], reference[i]) - d(query[i], extra[k])))))
    return torch.stack(terms).mean()
