"""Recall with positives and semi-positives (docs/conventions.md "Ranks and Recall@K", "VIGOR hit rate") against
brute force."""
import pytest
import torch
import torch.nn.functional as F
from geoloc.eval import recall_at_k
from geoloc.eval.recall import one_percent_k

from helpers.descriptor_data import vigor_like_data as data
from helpers.ranking import ranks_of

BACKENDS = ["torch", pytest.param("faiss", marks=pytest.mark.filterwarnings("ignore"))]


def brute_force(query, reference, positives, semi, ks):
    """Python loops straight from the definitions. The hit is VIGOR's code rule (`validate_top`, Sample4Geo's
    `calculate_scores`): no reference outside the positive and its semi-positives strictly above the positive."""
    n = len(reference)
    ranks, hits = [], []
    for i in range(len(query)):
        s = [float(query[i] @ reference[j]) for j in range(n)]
        p = int(positives[i])
        ranks.append(sum(1 for j in range(n) if j != p and s[j] > s[p]))
        members = {p} | {int(x) for x in semi[i] if x >= 0}
        hits.append(all(s[j] <= s[p] for j in range(n) if j not in members))
    out = {f"R@{k}": sum(r < k for r in ranks) / len(ranks) for k in ks}
    out["R@1%"] = sum(r < one_percent_k(n) for r in ranks) / len(ranks)
    out["hit_rate"] = sum(hits) / len(hits)
    return out


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("q,n", [(40, 250), (300, 120)])  # fewer and more queries than references
def test_matches_brute_force(backend, q, n):
    query, reference, positives, semi = data(q, n)
    got = recall_at_k(query, reference, ks=(1, 3, 10), backend=backend, chunk_size=16, positives=positives,
                      semi_positives=semi)
    want = brute_force(query, reference, positives, semi, (1, 3, 10))
    assert got == pytest.approx(want, abs=1e-12)
    assert 0 < got["R@1"] < got["hit_rate"] < 1  # the data exercise both cases (a semi-positive hit that is no R@1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_identity_positives_are_the_one_to_one_protocol(backend):
    query, reference, _, _ = data(30, 80, seed=1)
    reference[:30] = F.normalize(reference[:30] + query, dim=1)
    plain = recall_at_k(query, reference, backend=backend)
    assert recall_at_k(query, reference, backend=backend, positives=torch.arange(30)) == plain
    with_empty_semi = recall_at_k(query, reference, backend=backend, positives=torch.arange(30),
                                  semi_positives=-torch.ones(30, 2, dtype=torch.long))
    assert with_empty_semi.pop("hit_rate") == plain["R@1"] and with_empty_semi == plain


def test_a_semi_positive_on_top_is_a_hit_but_not_a_rank_zero():
    query = torch.tensor([[1.0, 0.0]])
    reference = F.normalize(torch.tensor([[0.6, 0.8], [1.0, 0.1], [0.0, 1.0]]), dim=1)
    out = recall_at_k(query, reference, ks=(1, 2), positives=[0], semi_positives=[[1, -1]])
    assert out["R@1"] == 0.0 and out["R@2"] == 1.0 and out["hit_rate"] == 1.0
    ranks, hits = ranks_of(query, reference, positives=[0], semi_positives=[[2, -1]])
    assert ranks.tolist() == [1] and hits.tolist() == [False]  # reference 1 beats both positive and semi


def test_shared_references_need_no_one_to_one_gallery():
    query, reference, positives, _ = data(50, 5, seed=2)
    assert set(recall_at_k(query, reference, positives=positives)) == {"R@1", "R@5", "R@10", "R@1%"}
    with pytest.raises(ValueError, match="positives="):
        recall_at_k(query, reference)


@pytest.mark.parametrize("kwargs,message", [
    ({"positives": [0, 1]}, "shape"),
    ({"positives": [0, 1, 9]}, r"query 2 .* \[0, 5\)"),
    ({"positives": [0.0, 1.0, 2.0]}, "integer"),
    ({"positives": [0, 1, 2], "semi_positives": [[0], [1]]}, r"\(3, S\)"),
    ({"positives": [0, 1, 2], "semi_positives": [[0], [-2], [1]]}, r"semi_positives of query 1"),
])
def test_bad_indices_are_named(kwargs, message):
    query, reference, _, _ = data(3, 5, seed=3)
    with pytest.raises((ValueError, TypeError), match=message):
        recall_at_k(query, reference, **kwargs)
