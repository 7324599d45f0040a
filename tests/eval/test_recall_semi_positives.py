"""Edges of recall with positives that the random data of test_recall_positives.py do not reach: a semi-positive
at reference index 0, the hit rate's rule with a semi-positive first, exact ties in the hit rate, hit rate across
reference blocks, and index checks."""
import pytest
import torch
from geoloc.eval import recall_at_k, scoring
from test_recall_positives import BACKENDS, brute_force, data

from helpers.ranking import ranks_of

# Exactly representable unit rows. Query 0: its semi-positive reference 0 scores 1, then reference 3 (a negative)
# 0.8, then its positive (reference 2) 0.6: VIGOR's code rule says miss (a negative is above the positive), the
# "top-1 is the positive or a semi-positive" reading would say hit. Query 1's positive (4) ties with reference 5
# at 1: a tie counts in the query's favour, for the rank and for the hit.
QUERY = torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0]], dtype=torch.float64)
REFERENCE = torch.tensor([[1.0, 0, 0, 0], [-1.0, 0, 0, 0], [0.6, 0.8, 0, 0], [0.8, 0, 0.6, 0], [0, 1.0, 0, 0],
                          [0, 1.0, 0, 0]], dtype=torch.float64)
POSITIVES = torch.tensor([2, 4])
SEMI = torch.tensor([[0, -1], [-1, -1]])


@pytest.mark.parametrize("backend", BACKENDS)
def test_semi_positive_zero_and_ties(backend):
    got = recall_at_k(QUERY, REFERENCE, ks=(1, 3), backend=backend, positives=POSITIVES, semi_positives=SEMI)
    assert got == brute_force(QUERY, REFERENCE, POSITIVES, SEMI, (1, 3))
    assert got == {"R@1": 0.5, "R@3": 1.0, "R@1%": 0.5, "hit_rate": 0.5}
    ranks, hits = ranks_of(QUERY, REFERENCE, positives=POSITIVES, semi_positives=SEMI)
    assert ranks.tolist() == [2, 0] and hits.tolist() == [False, True]


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_semi_positive_then_a_negative_then_the_positive_is_a_miss(backend):
    """VIGOR's code rule (train_SAFA.py validate_top; Sample4Geo evaluate/vigor.py calculate_scores): the semi-
    positives are masked out, and any other reference strictly above the positive is a miss, whatever is top-1."""
    query = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    reference = torch.tensor([[0.6, 0.8, 0, 0], [1.0, 0, 0, 0], [0.8, 0, 0.6, 0], [0, 0, 0, 1.0]],
                             dtype=torch.float64)  # scores: 0.6 (positive), 1 (semi), 0.8 (negative), 0
    out = recall_at_k(query, reference, ks=(1, 3), backend=backend, positives=[0], semi_positives=[[1]])
    assert out["hit_rate"] == 0.0 and out["R@1"] == 0.0 and out["R@3"] == 1.0  # rank 2
    # without the negative in between, the semi-positive on top is a hit
    out = recall_at_k(query, reference[[0, 1, 3]], ks=(1,), backend=backend, positives=[0], semi_positives=[[1]])
    assert out["hit_rate"] == 1.0 and out["R@1"] == 0.0


def test_hit_rate_counts_every_reference_block(monkeypatch):
    query, reference, positives, semi = data(60, 90, seed=3)
    want = brute_force(query, reference, positives, semi, (1, 5))
    monkeypatch.setattr(scoring, "SCORE_BUDGET", 7 * 1024)  # 13 blocks of 7 references
    assert recall_at_k(query, reference, ks=(1, 5), positives=positives, semi_positives=semi) == \
        pytest.approx(want, abs=1e-12)


@pytest.mark.parametrize("kwargs,err,match", [
    (dict(positives=torch.tensor([True, False])), TypeError, "positives must hold integer reference indices"),
    (dict(positives=torch.tensor([0, 6])), ValueError, r"positives of query 1 is 6: indices must lie in \[0, 6\)"),
    (dict(positives=torch.tensor([0, 1]), semi_positives=torch.tensor([[6], [-1]])), ValueError,
     r"semi_positives of query 0 is \[6\]: indices must lie in \[-1, 6\)"),
])
def test_bad_indices_say_which_and_where(kwargs, err, match):
    with pytest.raises(err, match=match):
        recall_at_k(QUERY, REFERENCE, **kwargs)


def test_one_to_one_needs_a_reference_per_query():
    query = torch.tensor([[1.0, 0], [0, 1.0], [1.0, 0], [0, 1.0]])  # 4 queries of dimension 2: fewer than 4
    reference = torch.tensor([[1.0, 0], [0, 1.0], [1.0, 0]])
    for fn in (recall_at_k, ranks_of):
        with pytest.raises(ValueError, match="got 4 queries and only 3 references"):
            fn(query, reference)
