"""Seeded descriptor sets with known structure, for the retrieval-metric tests."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def labelled_data(n_query=50, n_labels=30, per_label=4, n_junk=6, dtype=torch.float64, seed=0):
    """Several references per label, queries pulled towards theirs (so ranks spread), some junk references."""
    g = torch.Generator().manual_seed(seed)
    reference_labels = torch.cat([torch.arange(n_labels).repeat_interleave(per_label), -torch.ones(n_junk).long()])
    reference_labels = reference_labels[torch.randperm(len(reference_labels), generator=g)]
    query_labels = torch.randint(0, n_labels, (n_query,), generator=g)
    centres = torch.randn(n_labels, 16, generator=g, dtype=torch.float64)
    reference = torch.randn(len(reference_labels), 16, generator=g, dtype=torch.float64)
    known = reference_labels >= 0
    reference[known] += 0.8 * centres[reference_labels[known]]
    query = torch.randn(n_query, 16, generator=g, dtype=torch.float64) + 0.8 * centres[query_labels]
    return F.normalize(query, dim=1).to(dtype), F.normalize(reference, dim=1).to(dtype), query_labels, \
        reference_labels


def vigor_like_data(q, n, d=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    query = F.normalize(torch.randn(q, d, generator=g, dtype=torch.float64), dim=1)
    reference = F.normalize(torch.randn(n, d, generator=g, dtype=torch.float64), dim=1)
    positives = torch.randint(0, n, (q,), generator=g)
    reference[positives] = F.normalize(reference[positives] + 1.5 * query, dim=1)  # positives nearer than chance
    semi = torch.randint(-1, n, (q, 3), generator=g)
    near = semi[::3, 0]  # every third query's first semi-positive near it too (overlapping VIGOR tiles)
    reference[near[near >= 0]] = F.normalize(reference[near[near >= 0]] + 2.0 * query[::3][near >= 0], dim=1)
    return query, reference, positives, semi


def low_rank_pairs(n_reference: int, n_query: int, dim: int, noise: float, seed: int, rank: int = 8):
    """Unit float32 numpy descriptors of intrinsic dimension `rank` in `dim` (reference = z W plus a little
    isotropic noise); query i is reference i's latent code plus `noise`, mapped by the same W. What the FAISS gallery
    kinds are tested on: clustered, as learned descriptors are, so IVF and PQ have structure to use."""
    import numpy as np

    def unit(x):
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)

    rng = np.random.default_rng(seed)
    w = rng.standard_normal((rank, dim)).astype(np.float32)
    z = rng.standard_normal((n_reference, rank)).astype(np.float32)
    reference = unit(z @ w + 0.05 * rng.standard_normal((n_reference, dim)).astype(np.float32))
    query = unit((z[:n_query] + noise * rng.standard_normal((n_query, rank)).astype(np.float32)) @ w)
    return query, reference
