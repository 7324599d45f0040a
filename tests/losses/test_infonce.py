"""info_nce against a brute-force loop (docs/conventions.md "Symmetric InfoNCE") and torch's own cross-entropy."""
import math

import pytest
import torch
import torch.nn.functional as F
from geoloc.losses import InfoNCELoss, info_nce


def unit_rows(b, d, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return F.normalize(torch.randn(b, d, generator=g, dtype=dtype), dim=1)


def brute_force(query, reference, t, labels=None, eps=0.0):
    """One softmax per anchor, both directions, written from the definition with Python loops."""
    b = len(query)
    total = 0.0
    for anchors, others in ((query, reference), (reference, query)):
        for i in range(b):
            # the candidates of anchor i: its match, and every j whose place differs
            cand = [j for j in range(b) if j == i or labels is None or labels[j] != labels[i]]
            s = [float(anchors[i] @ others[j]) / t for j in cand]
            log_z = math.log(sum(math.exp(v) for v in s))
            log_p = {j: v - log_z for j, v in zip(cand, s)}
            total += (1 - eps) * -log_p[i] + eps * sum(-v for v in log_p.values()) / len(cand)
    return total / (2 * b)


@pytest.mark.parametrize("t", [0.07, 0.5])
@pytest.mark.parametrize("eps", [0.0, 0.1])
def test_matches_brute_force(t, eps):
    q, r = unit_rows(7, 5, 0), unit_rows(7, 5, 1)
    assert info_nce(q, r, t, label_smoothing=eps).item() == pytest.approx(brute_force(q, r, t, eps=eps), rel=1e-6)


@pytest.mark.parametrize("eps", [0.0, 0.1])
def test_same_place_pairs_are_no_negatives(eps):
    q, r = unit_rows(8, 5, 2), unit_rows(8, 5, 3)
    labels = torch.tensor([0, 1, 0, 2, 1, 3, 3, 4])
    got = info_nce(q, r, 0.1, labels=labels, label_smoothing=eps).item()
    assert got == pytest.approx(brute_force(q, r, 0.1, labels.tolist(), eps), rel=1e-6)
    assert got != pytest.approx(info_nce(q, r, 0.1, label_smoothing=eps).item(), rel=1e-3)
    distinct = torch.arange(8)  # all places distinct: the plain loss
    assert info_nce(q, r, 0.1, labels=distinct).item() == pytest.approx(info_nce(q, r, 0.1).item(), rel=1e-12)


def test_equals_torch_symmetric_cross_entropy_with_smoothing():
    q, r = unit_rows(6, 4, 4), unit_rows(6, 4, 5)
    logits = (q @ r.t()).float() / 0.2
    target = torch.arange(6)
    expected = (F.cross_entropy(logits, target, label_smoothing=0.1)
                + F.cross_entropy(logits.t(), target, label_smoothing=0.1)) / 2
    assert info_nce(q, r, 0.2, label_smoothing=0.1).item() == pytest.approx(expected.item(), rel=1e-5)


def test_rows_are_normalised_inside():
    q, r = unit_rows(5, 4, 6), unit_rows(5, 4, 7)
    assert info_nce(3 * q, 0.5 * r, 0.1).item() == pytest.approx(info_nce(q, r, 0.1).item(), rel=1e-6)


def test_learned_temperature_gets_a_gradient_and_fixed_one_does_not():
    q, r = unit_rows(6, 4, 8, torch.float32), unit_rows(6, 4, 9, torch.float32)
    learned = InfoNCELoss(temperature=0.07, learn_temperature=True)
    assert learned.temperature.item() == pytest.approx(0.07)
    learned(q, r).backward()
    assert learned.log_inv_temperature.grad is not None and learned.log_inv_temperature.grad.abs() > 0
    fixed = InfoNCELoss(temperature=0.07)
    assert list(fixed.parameters()) == [] and "log_inv_temperature" in fixed.state_dict()


def test_bad_arguments_are_named():
    q = unit_rows(4, 3, 0)
    with pytest.raises(ValueError, match="B x D"):
        info_nce(q, q[:3])
    with pytest.raises(ValueError, match="labels"):
        info_nce(q, q, labels=torch.zeros(3))
    with pytest.raises(ValueError, match="temperature"):
        info_nce(q, q, temperature=0.0)
