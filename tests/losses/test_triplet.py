"""soft_margin_triplet against a brute-force loop over triplets (docs/conventions.md "Soft-margin triplet")."""
import math

import pytest
import torch
import torch.nn.functional as F
from geoloc.losses import soft_margin_triplet

from helpers.brute_force import brute_force


def unit_rows(b, d, dtype, seed):
    g = torch.Generator().manual_seed(seed)
    return F.normalize(torch.randn(b, d, generator=g, dtype=dtype), dim=1)


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
@pytest.mark.parametrize("alpha", [10.0, 1.0])
def test_in_batch_matches_brute_force(dtype, tol, alpha):
    q, r = unit_rows(6, 8, dtype, 0), unit_rows(6, 8, dtype, 1)
    r = F.normalize(r + 2 * q, dim=1)  # some structure: matches closer than chance
    got = soft_margin_triplet(q, r, alpha=alpha)
    assert got.dtype == dtype and got.ndim == 0
    torch.testing.assert_close(got, brute_force(q, r, alpha), rtol=tol, atol=tol)


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
@pytest.mark.parametrize("with_mask", [False, True])
def test_extra_negatives_match_brute_force(dtype, tol, with_mask):
    q, r, extra = unit_rows(5, 8, dtype, 2), unit_rows(5, 8, dtype, 3), unit_rows(7, 8, dtype, 4)
    mask = torch.rand(5, 7, generator=torch.Generator().manual_seed(5)) > 0.4 if with_mask else None
    got = soft_margin_triplet(q, r, extra_negatives=extra, extra_mask=mask)
    torch.testing.assert_close(got, brute_force(q, r, 10.0, extra, mask), rtol=tol, atol=tol)


def test_term_count_is_2b_b_minus_1_plus_kept_extras():
    # With every distance equal, each term is softplus(0) = log 2 and the mean is too; mixing in terms of another
    # value shows the weights: one query-reference extra term per kept (query, negative) pair.
    b, d = 4, 3
    q = torch.zeros(b, d)
    q[:, 0] = 1
    r = q.clone()  # d_pos = 0 and every in-batch d_neg = 0: in-batch terms are log 2
    extra = torch.tensor([[-1.0, 0, 0]])  # d = 4: term softplus(-40) ~ 0
    mask = torch.tensor([[True], [False], [True], [False]])
    got = soft_margin_triplet(q, r, extra_negatives=extra, extra_mask=mask)
    n_in = 2 * b * (b - 1)
    expected = (n_in * math.log(2) + 2 * F.softplus(torch.tensor(-40.0)).item()) / (n_in + 2)
    assert got.item() == pytest.approx(expected, rel=1e-6)


def test_fully_masked_extras_equal_no_extras():
    q, r = unit_rows(4, 6, torch.float64, 6), unit_rows(4, 6, torch.float64, 7)
    extra = unit_rows(3, 6, torch.float64, 8)
    none = torch.zeros(4, 3, dtype=torch.bool)
    torch.testing.assert_close(soft_margin_triplet(q, r, extra_negatives=extra, extra_mask=none),
                               soft_margin_triplet(q, r))


def test_gradients_match_brute_force():
    # Through F.normalize, as in a model: on the sphere 2 - 2a.b and ||a - b||^2 agree, and so do the gradients
    # that reach the raw descriptors.
    g = torch.Generator().manual_seed(9)
    raw = [torch.randn(n, 5, generator=g, dtype=torch.float64) for n in (4, 4, 3)]
    mask = torch.tensor([[1, 0, 1], [1, 1, 1], [0, 0, 1], [1, 1, 0]], dtype=torch.bool)
    grads = []
    for fn in (soft_margin_triplet, brute_force):
        leaves = [t.clone().requires_grad_(True) for t in raw]
        q, r, e = (F.normalize(t, dim=1) for t in leaves)
        fn(q, r, 10.0, e, mask).backward()
        grads.append([t.grad for t in leaves])
    for got, ref in zip(*grads):
        torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-12)


def test_gradcheck():
    q, r = unit_rows(3, 4, torch.float64, 12).requires_grad_(), unit_rows(3, 4, torch.float64, 13).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: soft_margin_triplet(a, b), (q, r))


def test_large_alpha_is_finite():
    # softplus, not log(1 + exp): a hard triplet with alpha * gap = 4000 must not overflow.
    q = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    r = torch.tensor([[-1.0, 0.0], [1.0, 0.0]])
    loss = soft_margin_triplet(q, r, alpha=1000.0)
    assert torch.isfinite(loss) and loss.item() > 100


def test_half_precision_is_computed_in_float32():
    q, r = unit_rows(4, 8, torch.float32, 14), unit_rows(4, 8, torch.float32, 15)
    got = soft_margin_triplet(q.bfloat16(), r.bfloat16())
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, soft_margin_triplet(q, r), rtol=2e-2, atol=2e-2)


def test_single_pair_with_one_kept_queue_negative_is_that_term():
    q, r = unit_rows(1, 4, torch.float64, 17), unit_rows(1, 4, torch.float64, 18)
    extra = unit_rows(2, 4, torch.float64, 19)
    mask = torch.tensor([[False, True]])
    got = soft_margin_triplet(q, r, extra_negatives=extra, extra_mask=mask)
    torch.testing.assert_close(got, brute_force(q, r, 10.0, extra, mask))  # one term, the mean of itself


def test_extra_negatives_are_cast_to_the_descriptors_dtype():
    q, r = unit_rows(3, 4, torch.float32, 20), unit_rows(3, 4, torch.float32, 21)
    extra = unit_rows(2, 4, torch.float64, 22)  # a float64 queue beside float32 descriptors
    got = soft_margin_triplet(q, r, extra_negatives=extra)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, soft_margin_triplet(q, r, extra_negatives=extra.float()))


def test_single_pair_without_negatives_is_zero():
    q = unit_rows(1, 4, torch.float32, 16).requires_grad_()
    loss = soft_margin_triplet(q, q.detach())
    assert loss.item() == 0.0
    loss.backward()


@pytest.mark.parametrize("kwargs,match", [
    (dict(query=torch.zeros(3, 4), reference=torch.zeros(2, 4)), "B x D"),
    (dict(query=torch.zeros(3), reference=torch.zeros(3)), "B x D"),
    (dict(query=torch.zeros(3, 4), reference=torch.zeros(3, 4), extra_negatives=torch.zeros(2, 5)), "Q x 4"),
    (dict(query=torch.zeros(3, 4), reference=torch.zeros(3, 4), extra_negatives=torch.zeros(2, 4),
          extra_mask=torch.ones(2, 3, dtype=torch.bool)), "extra_mask"),
    (dict(query=torch.zeros(3, 4), reference=torch.zeros(3, 4), extra_negatives=torch.zeros(2, 4),
          extra_mask=torch.ones(3, 2)), "bool"),
    (dict(query=torch.zeros(3, 4), reference=torch.zeros(3, 4), extra_mask=torch.ones(3, 2, dtype=torch.bool)),
     "without extra_negatives"),
])
def test_bad_inputs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        soft_margin_triplet(**kwargs)


def brute_force_labelled(query, reference, labels, alpha=10.0):
    """Every triplet whose negative shows another place than the anchor's, written out one by one."""
    def d(a, b):
        return ((a - b) ** 2).sum()

    terms = []
    for i in range(len(query)):
        for j in range(len(query)):
            if i == j or labels[i] == labels[j]:
                continue
            terms.append(torch.log1p(torch.exp(alpha * (d(query[i], reference[i]) - d(query[i], reference[j])))))
            terms.append(torch.log1p(torch.exp(alpha * (d(reference[i], query[i]) - d(reference[i], query[j])))))
    return torch.stack(terms).mean()


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
def test_pairs_of_one_place_are_not_each_others_negatives(dtype, tol):
    """Two VIGOR panoramas with the same positive tile: their terms against each other are left out."""
    g = torch.Generator().manual_seed(5)
    query = F.normalize(torch.randn(7, 6, generator=g, dtype=dtype), dim=1)
    reference = F.normalize(torch.randn(7, 6, generator=g, dtype=dtype), dim=1)
    labels = torch.tensor([0, 1, 1, 2, 3, 3, 3])
    loss = soft_margin_triplet(query, reference, labels=labels)
    torch.testing.assert_close(loss, brute_force_labelled(query, reference, labels), atol=tol, rtol=tol)
    assert abs(loss - brute_force(query, reference)) > 1e-3  # the labels change the loss on this batch


def test_distinct_labels_give_the_unlabelled_loss_bit_for_bit():
    g = torch.Generator().manual_seed(6)
    query = F.normalize(torch.randn(9, 5, generator=g), dim=1)
    reference = F.normalize(torch.randn(9, 5, generator=g), dim=1)
    assert torch.equal(soft_margin_triplet(query, reference, labels=torch.arange(9) * 3),
                       soft_margin_triplet(query, reference))


def test_labels_of_the_wrong_shape_are_refused():
    x = F.normalize(torch.randn(4, 3), dim=1)
    with pytest.raises(ValueError, match=r"labels must have shape \(4,\)"):
        soft_margin_triplet(x, x, labels=torch.arange(3))
