"""any_view_infonce against a brute-force loop, and the errors when the extra views are missing."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from geoloc import registry
from geoloc.losses.any_view import heading_contrast
from geoloc.losses.infonce import info_nce


def brute_heading_contrast(q, r, w, t, labels):
    q, r, w = (F.normalize(x, dim=1) for x in (q, r, w))
    b, rows, cols = len(q), [], []
    for i in range(b):
        # query i against the references: other pairs of its place are left out
        kept = [j for j in range(b) if j == i or labels[j] != labels[i]]
        logits = [float(q[i] @ r[j]) / t for j in kept]
        rows.append(-(logits[kept.index(i)] - math.log(sum(math.exp(x) for x in logits))))
        # reference i against every query of another place, itself, and every wrong placement
        logits = [float(r[i] @ q[j]) / t for j in kept] + [float(r[i] @ w[j]) / t for j in range(b)]
        cols.append(-(logits[kept.index(i)] - math.log(sum(math.exp(x) for x in logits))))
    return (sum(rows) / b + sum(cols) / b) / 2


def batch(b=6, d=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    q, r, w = (torch.randn(b, d, generator=g, dtype=torch.float64) for _ in range(3))
    return q, r, w, torch.tensor([0, 1, 1, 2, 3, 3])


def test_heading_contrast_matches_a_brute_force_loop():
    q, r, w, labels = batch()
    got = heading_contrast(q, r, w, 0.3, labels)
    assert float(got) == pytest.approx(brute_heading_contrast(q, r, w, 0.3, labels.tolist()), rel=1e-6)


def test_a_wrong_placement_that_scores_like_the_true_one_costs_more():
    q, r, w, labels = batch()
    far = heading_contrast(q, r, -q, 0.3, labels)  # wrong views opposite to the true ones
    near = heading_contrast(q, r, q.clone(), 0.3, labels)  # wrong views identical to the true ones
    assert float(near) > float(far) + 0.1


def test_the_loss_adds_the_full_view_and_consistency_terms_with_their_weights():
    q, r, w, labels = batch()
    f = torch.randn_like(q)
    loss = registry.build("loss", {"name": "any_view_infonce", "learn_temperature": False, "temperature": 0.2,
                                   "label_smoothing": 0.0, "full_weight": 0.5, "consistency_weight": 2.0}, dim=5)
    out = loss(q, r, labels, query_views=torch.stack([w, f], 1))
    want = (brute_heading_contrast(q, r, w, 0.2, labels.tolist()) + 0.5 * float(info_nce(f, r, 0.2, labels))
            + 2.0 * float(info_nce(q, f, 0.2, labels)))
    assert float(out["loss"]) == pytest.approx(want, rel=1e-6)


def test_the_loss_refuses_a_batch_without_the_two_extra_views():
    q, r, w, labels = batch()
    loss = registry.build("loss", {"name": "any_view_infonce"}, dim=5)
    with pytest.raises(ValueError, match="views=any_view"):
        loss(q, r, labels)
    with pytest.raises(ValueError, match="views=any_view"):
        loss(q, r, labels, query_views=w[:, None])
