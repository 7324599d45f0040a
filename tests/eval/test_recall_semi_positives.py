"""Edges of recall with positives that the random data of test_recall_positives.py do not reach: a semi-positive
at reference index 0, exact ties in the hit rate, hit rate across reference blocks, and index checks."""
import pytest
import torch
from geoloc.eval import recall_at_k
from geoloc.eval.recall import retrieval_ranks
from test_recall_positives import BACKENDS, brute_force, data

# Exactly representable unit rows. Query 0's positive (reference 2) scores 0.6 and its semi-positive reference 0
# scores 1, so only the semi-positive makes it a hit over reference 3 (0.8). Query 1's positive (4) ties with
# reference 5 at 1: a tie counts in the query's favour, for the rank and for the hit.
QUERY = torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0]], dtype=torch.float64)
REFERENCE = torch.tensor([[1.0, 0, 0, 0], [-1.0, 0, 0, 0], [0.6, 0.8, 0, 0], [0.8, 0, 0.6, 0], [0, 1.0, 0, 0],
                          [0, 1.0, 0, 0]], dtype=torch.float64)
POSITIVES = torch.tensor([2, 4])
SEMI = torch.tensor([[0, -1], [-1, -1]])


@pytest.mark.parametrize("backend", BACKENDS)
def test_semi_positive_zero_and_ties(backend):
    got = recall_at_k(QUERY, REFERENCE, ks=(1, 3), backend=backend, positives=POSITIVES, semi_positives=SEMI)
    assert got == brute_force(QUERY, REFERENCE, POSITIVES, SEMI, (1, 3))
    assert got == {"R@1": 0.5, "R@3": 1.0, "R@1%": 0.5, "hit_rate": 1.0}
    ranks, hits = retrieval_ranks(QUERY, REFERENCE, positives=POSITIVES, semi_positives=SEMI)
    assert ranks.tolist() == [2, 0] and hits.tolist() == [True, True]


def test_hit_rate_counts_every_reference_block(monkeypatch):
    import geoloc.eval.recall as recall_mod

    query, reference, positives, semi = data(60, 90, seed=3)
    want = brute_force(query, reference, positives, semi, (1, 5))
    monkeypatch.setattr(recall_mod, "_chunk_rows", lambda n_cols: 7)  # 13 blocks of references
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
    for fn in (recall_at_k, retrieval_ranks):
        with pytest.raises(ValueError, match="got 4 queries and only 3 references"):
            fn(query, reference)
