"""University-1652's AP and label recall against a per-query loop over the full ranking, hand values, ties, junk."""
import pytest
import torch
import torch.nn.functional as F
from geoloc.eval.average_precision import mean_average_precision
from geoloc.eval.recall import one_percent_k, recall_at_k

from helpers.descriptor_data import labelled_data as data
from helpers.ranking import ranks_of


def brute_force(query, reference, query_labels, reference_labels, ks):
    """The benchmark's compute_mAP written as a loop: rank the whole gallery (junk, label -1, removed; a relevant
    reference before irrelevant ones of equal score), then the trapezoid sum over the relevant ranks."""
    aps, firsts = [], []
    for i in range(len(query)):
        kept = [j for j in range(len(reference)) if int(reference_labels[j]) != -1]
        score = {j: float(query[i] @ reference[j]) for j in kept}
        relevant = {j for j in kept if int(reference_labels[j]) == int(query_labels[i])}
        ranking = sorted(kept, key=lambda j: (-score[j], j not in relevant))
        rows_good = [pos for pos, j in enumerate(ranking) if j in relevant]
        ap = 0.0
        for n, row in enumerate(rows_good):
            precision = (n + 1) / (row + 1)
            old_precision = n / row if row != 0 else 1.0
            ap += (old_precision + precision) / 2 / len(rows_good)
        aps.append(ap)
        firsts.append(rows_good[0])
    out = {"AP": sum(aps) / len(aps)}
    cutoffs = {f"R@{k}": k for k in ks} | {"R@1%": one_percent_k(len(reference))}
    out.update({key: sum(f < k for f in firsts) / len(firsts) for key, k in cutoffs.items()})
    return out


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_the_loop(dtype):
    query, reference, ql, rl = data(dtype=dtype)
    got = mean_average_precision(query, reference, ql, rl, ks=(1, 5, 10))
    want = brute_force(query.double(), reference.double(), ql, rl, (1, 5, 10))
    assert got == pytest.approx(want, abs=1e-12)
    assert 0.1 < got["AP"] < got["R@5"] < 1  # several relevant references, spread over the ranking


def test_chunking_and_precision_do_not_change_the_result():
    query, reference, ql, rl = data(seed=1)
    whole = mean_average_precision(query, reference, ql, rl, ks=(1, 3))
    for chunk_size in (1, 7, 50):
        assert mean_average_precision(query, reference, ql, rl, ks=(1, 3), chunk_size=chunk_size) == whole
    as_float32 = mean_average_precision(query.float(), reference.float(), ql.numpy(), rl.numpy(), ks=(1, 3))
    assert as_float32 == pytest.approx(whole, abs=1e-6)


def test_perfect_ranking_is_one():
    query, reference, ql, rl = data(n_junk=0, seed=2)
    reference = F.normalize(torch.eye(16, dtype=torch.float64)[rl % 16] + 0.01 * reference, dim=1)
    query = torch.eye(16, dtype=torch.float64)[ql % 16]
    ql, rl = ql % 16, rl % 16
    assert mean_average_precision(query, reference, ql, rl, ks=(1,)) == {"AP": 1.0, "R@1": 1.0, "R@1%": 1.0}


def test_hand_values_follow_the_trapezoid_not_the_plain_mean():
    # query (1, 0); references by score: 1.0 (label 7), 0.8 (label 3), 0.6 (label 7), 0.0 (label 3)
    query = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    reference = torch.tensor([[0.6, 0.8], [1.0, 0.0], [0.0, 1.0], [0.8, 0.6]], dtype=torch.float64)
    labels = torch.tensor([7, 7, 3, 3])
    # label 3 is at ranks 1 and 3: (1/2)((0/1 + 1/2)/2 + (1/3 + 2/4)/2) = 1/8 + 5/24; scikit-learn: (1/2 + 2/4)/2
    got = mean_average_precision(query, reference, [3], labels, ks=(1, 2))
    assert got == pytest.approx({"AP": 1 / 8 + 5 / 24, "R@1": 0.0, "R@2": 1.0, "R@1%": 0.0}, abs=1e-15)
    # one relevant reference at rank 1: (0/1 + 1/2)/2 = 0.25 (scikit-learn would give 0.5)
    got = mean_average_precision(query, reference[1:], [3], [7, 9, 3], ks=(1,))  # by score: 7, 3, 9
    assert got["AP"] == pytest.approx(0.25, abs=1e-15)


@pytest.mark.parametrize("n,g", [(5, 1), (5, 2), (9, 3)])
def test_worst_ranking_has_its_closed_form(n, g):
    # the g relevant references score lowest: ranks n-g .. n-1
    query = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    angles = torch.linspace(0, 3.0, n, dtype=torch.float64)
    reference = torch.stack([angles.cos(), angles.sin()], dim=1)
    labels = torch.tensor([0] * (n - g) + [1] * g)
    want = sum(((i / (n - g + i) if n - g + i else 1.0) + (i + 1) / (n - g + i + 1)) / 2 for i in range(g)) / g
    got = mean_average_precision(query, reference, [1], labels)
    assert got["AP"] == pytest.approx(want, abs=1e-15) and got["R@1"] == 0.0


def test_a_tie_counts_in_the_querys_favour():
    # reference 0 (label 5) and reference 1 (label 9) score exactly 1 for the query of label 9
    query = torch.tensor([[1.0, 0.0]])
    reference = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    got = mean_average_precision(query, reference, [9], [5, 9, 9], ks=(1,))
    # relevant ranks 0 and 2 (not 1 and 2): (1/2)(1 + (1/2 + 2/3)/2)
    assert got == pytest.approx({"AP": (1 + (1 / 2 + 2 / 3) / 2) / 2, "R@1": 1.0, "R@1%": 1.0}, abs=1e-15)


def test_one_reference_per_label_is_recall_with_positives():
    # drone -> satellite: one satellite per building, so label recall is recall_at_k with that positive, and
    # the AP of rank r > 0 is (0/r + 1/(r+1))/2
    g = torch.Generator().manual_seed(3)
    reference = F.normalize(torch.randn(40, 8, generator=g, dtype=torch.float64), dim=1)
    positives = torch.randint(0, 40, (120,), generator=g)
    query = F.normalize(torch.randn(120, 8, generator=g, dtype=torch.float64) + reference[positives], dim=1)
    got = mean_average_precision(query, reference, positives, torch.arange(40), ks=(1, 5))
    assert {k: v for k, v in got.items() if k != "AP"} == recall_at_k(query, reference, (1, 5), positives=positives)
    ranks = ranks_of(query, reference, positives=positives).double()
    assert len(set(ranks.tolist())) > 5
    per_query = torch.where(ranks > 0, 1 / (ranks + 1) / 2, torch.ones_like(ranks))
    assert got["AP"] == pytest.approx(float(per_query.mean()), abs=1e-12)


def test_junk_references_are_left_out():
    query, reference, ql, rl = data(n_junk=0, seed=4)
    clean = mean_average_precision(query, reference, ql, rl, ks=(1, 5))
    junk = query[:8] + 0.01  # right on top of queries: they would rank first if they counted
    with_junk = mean_average_precision(query, torch.cat([junk, reference]), ql,
                                       torch.cat([-torch.ones(8, dtype=torch.long), rl]), ks=(1, 5))
    assert with_junk == pytest.approx(clean, abs=1e-12)
    assert mean_average_precision(query, torch.cat([junk, reference]), ql, torch.cat([ql[:8], rl]),
                                  ks=(1, 5))["AP"] != pytest.approx(clean["AP"])  # they would matter otherwise


@pytest.mark.parametrize("kwargs,err,match", [
    (dict(query_labels=[0, 1, 7]), ValueError, r"query 2 has label 7, which no reference has.*\(1 such"),
    (dict(query_labels=[0, 1, -1]), ValueError, r"query 2 has label -1.*junk"),
    (dict(query_labels=[0, 1]), ValueError, r"query_labels must have shape \(3,\)"),
    (dict(reference_labels=[0, 1, 2, 2.0]), TypeError, "reference_labels must hold integer"),
    (dict(reference_labels=[0, 1, 2]), ValueError, r"reference_labels must have shape \(4,\)"),
    (dict(ks=(0,)), ValueError, "ks must be"),
    (dict(chunk_size=0), ValueError, "chunk_size must be >= 1"),
])
def test_bad_input_names_the_argument(kwargs, err, match):
    args = dict(query=torch.eye(4)[:3], reference=torch.eye(4), query_labels=[0, 1, 2],
                reference_labels=[0, 1, 2, 2]) | kwargs
    with pytest.raises(err, match=match):
        mean_average_precision(**args)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_on_the_gpu_matches_the_cpu():
    query, reference, ql, rl = data(n_query=200, seed=5)
    want = mean_average_precision(query, reference, ql, rl, ks=(1, 5))
    assert mean_average_precision(query.cuda(), reference.cuda(), ql, rl, ks=(1, 5)) == pytest.approx(want, abs=1e-12)
