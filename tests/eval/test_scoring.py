"""The scorer (geoloc/eval/scoring.py, candidates.py) against loops over references: the one rank rule for every
relevance kind with exact ties, VIGOR's hit, every relevant reference's position (AP), the top-k tie rule, K
candidates per query, any blocking, candidate lists, and the one-to-one ranks exactly as computed before."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from geoloc.data.geo import distance_m, offset_to_latlon
from geoloc.data.relevance import Relevance
from geoloc.eval import scoring
from geoloc.eval.average_precision import average_precision
from geoloc.eval.candidates import merge_headings, rank_candidates
from geoloc.eval.recall import recall_summary
from geoloc.eval.scoring import rank, relevant_scores, top_k
from geoloc.tasks.crossview.heading import heading_metrics
from geoloc.tasks.crossview.views import circular_error_deg

from helpers.ranking import one_to_one_ranks_before, ranks_of

# (query chunk, score budget): one block; 3 queries x 5 references; one query x 3 references
BLOCKINGS = [(None, 1 << 25), (3, 15), (1, 3)]
RADIUS_ALONE_M = 12.0  # small enough that some queries have no reference this near


def exact_rows(n: int, d: int = 8, seed: int = 0) -> torch.Tensor:
    """Unit rows of four entries +-0.5: every product is a multiple of 1/4, exact in any summation order, so
    equal scores are exact ties on every path."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(n, d, dtype=torch.float64)
    for i in range(n):
        x[i, torch.randperm(d, generator=g)[:4]] = 0.5 * (2 * torch.randint(0, 2, (4,), generator=g) - 1).double()
    return x


QUERY, REFERENCE = exact_rows(23, seed=1), exact_rows(37, seed=2)
QUERY[::3] = REFERENCE[:23:3]  # every third query is its reference's twin: rank 0, unless another ties above
SCORES = (QUERY @ REFERENCE.T).numpy()  # exact


def members(table, i) -> set[int]:
    return set() if table is None else {int(j) for j in table[i] if j >= 0}


def loop_counts(relevance: Relevance, i: int, target: float, relevant: set[int], ignored: set[int]) -> int:
    return sum(1 for j in range(SCORES.shape[1]) if j not in relevant | ignored and SCORES[i, j] > target)


def loop_rank(relevance: Relevance, hit: bool = False) -> list[int]:
    """rank_i = #{j not relevant, not ignored : s_ij > max relevant s_ig}, one reference at a time; a query with
    nothing relevant is past every K."""
    junk = set() if relevance.ignored_references is None else set(np.flatnonzero(relevance.ignored_references))
    out = []
    for i in range(SCORES.shape[0]):
        relevant = members(relevance.relevant, i)
        ignored = junk | (members(relevance.semi_positives, i) if hit else set())
        out.append(loop_counts(relevance, i, max(SCORES[i, g] for g in relevant), relevant, ignored)
                   if relevant else scoring.NO_RELEVANT)
    return out


def loop_positions(relevance: Relevance) -> list[list[int]]:
    """0-based positions of the relevant references in the full ranking (junk removed), a relevant reference
    before the non-relevant ones of its score."""
    junk = set() if relevance.ignored_references is None else set(np.flatnonzero(relevance.ignored_references))
    out = []
    for i in range(SCORES.shape[0]):
        relevant = members(relevance.relevant, i)
        kept = [j for j in range(SCORES.shape[1]) if j not in junk]
        ranking = sorted(kept, key=lambda j: (-SCORES[i, j], j not in relevant))
        out.append([pos for pos, j in enumerate(ranking) if j in relevant])
    return out


def raw_inputs() -> dict:
    g = torch.Generator().manual_seed(3)
    reference_labels = torch.randint(0, 6, (37,), generator=g)
    reference_labels[:6] = torch.arange(6)
    reference_labels[[6, 11]] = -1  # junk
    rng = np.random.default_rng(4)
    return dict(positives=torch.randint(0, 37, (23,), generator=g), semi=torch.randint(-1, 37, (23, 3), generator=g),
                query_labels=torch.randint(0, 6, (23,), generator=g), reference_labels=reference_labels,
                query_xy=rng.uniform(0, 100, (23, 2)), reference_xy=rng.uniform(0, 100, (37, 2)))


def relevances() -> dict[str, Relevance]:
    x = raw_inputs()
    latlon = [offset_to_latlon((41.88, -87.63), *xy.T) for xy in (x["query_xy"], x["reference_xy"])]
    return {
        "one_to_one": Relevance.one_to_one(23, 37),
        "positives": Relevance.from_positives(x["positives"], 37, x["semi"]),
        "labels": Relevance.from_labels(x["query_labels"], x["reference_labels"]),
        "radius_xy": Relevance.within_radius(x["positives"], x["query_xy"], x["reference_xy"], "xy", 25.0),
        "radius_latlon": Relevance.within_radius(x["positives"], *latlon, "latlon", 25.0),
        "radius_alone": Relevance.within_radius(None, x["query_xy"], x["reference_xy"], "xy", RADIUS_ALONE_M),
    }


def test_the_data_hold_ties_and_spread():
    ranks = loop_rank(relevances()["one_to_one"])
    assert len(set(ranks)) > 5 and 0 in ranks  # some queries first, others far down
    ties = sum(len(row) - len(set(row)) for row in SCORES.tolist())
    assert ties > 200  # many exact ties, at the positives too
    assert any(SCORES[i, j] == SCORES[i, i] for i in range(23) for j in range(37) if j != i)


@pytest.mark.parametrize("kind", ["one_to_one", "positives", "labels", "radius_xy", "radius_latlon", "radius_alone"])
@pytest.mark.parametrize("chunk,budget", BLOCKINGS)
@pytest.mark.parametrize("compare_targets", [0, 100])  # every target counted by the sort, or by comparison
def test_one_rank_rule_for_every_relevance_kind(monkeypatch, kind, chunk, budget, compare_targets):
    monkeypatch.setattr(scoring, "SCORE_BUDGET", budget)
    monkeypatch.setattr(scoring, "COMPARE_TARGETS", compare_targets)
    relevance = relevances()[kind]
    hits = relevance.semi_positives is not None
    found = rank(QUERY, REFERENCE, relevance, hits=hits, every_relevant=True, top=9, chunk_size=chunk)
    assert found.ranks.tolist() == loop_rank(relevance)
    if hits:
        assert found.hits.tolist() == [count == 0 for count in loop_rank(relevance, hit=True)]
    for i, want in enumerate(loop_positions(relevance)):
        got = found.relevant_ranks[i]
        assert got[got >= 0].tolist() == want, i
    for i in range(23):
        assert found.top_rows[i].tolist() == sorted(range(37), key=lambda j: (-SCORES[i, j], j))[:9], i
        assert found.top_scores[i].tolist() == sorted(SCORES[i], reverse=True)[:9]


def test_relevance_sets_are_what_each_kind_says():
    rel, x = relevances(), raw_inputs()
    for i in range(23):
        assert members(rel["one_to_one"].relevant, i) == {i}
        assert members(rel["positives"].relevant, i) == {int(x["positives"][i])}
        assert members(rel["positives"].semi_positives, i) == members(x["semi"], i)
        assert members(rel["labels"].relevant, i) == {j for j in range(37)
                                                      if x["reference_labels"][j] == x["query_labels"][i]}
        near = {j for j in range(37) if distance_m(x["query_xy"][i], x["reference_xy"][j], "xy") <= 25.0}
        assert members(rel["radius_xy"].relevant, i) == near | {int(x["positives"][i])}
        assert members(rel["radius_latlon"].relevant, i) == members(rel["radius_xy"].relevant, i)
        near = {j for j in range(37) if distance_m(x["query_xy"][i], x["reference_xy"][j], "xy") <= RADIUS_ALONE_M}
        assert members(rel["radius_alone"].relevant, i) == near
    assert rel["labels"].ignored_references.nonzero().flatten().tolist() == [6, 11]
    assert max(len(members(rel["radius_xy"].relevant, i)) for i in range(23)) > 2  # several per query
    assert rel["positives"].semi_positives is not None and rel["labels"].semi_positives is None


def test_a_relevant_reference_never_counts_against_itself_and_ties_favour_the_query():
    query = torch.tensor([[1.0, 0.0]])
    reference = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    for relevant in ([0], [1]):
        assert rank(query, reference, Relevance.from_positives(relevant, 3)).ranks.tolist() == [0]
    assert rank(query, reference, Relevance.from_positives([2], 3)).ranks.tolist() == [2]
    assert top_k(query, reference, 2)[1].tolist() == [[0, 1]]  # the lower row first among equal scores


@pytest.mark.parametrize("chunk,budget", BLOCKINGS)
def test_k_candidates_per_query_score_by_their_best(monkeypatch, chunk, budget):
    monkeypatch.setattr(scoring, "SCORE_BUDGET", budget)
    candidates = torch.stack([exact_rows(23, seed=s) for s in (5, 6, 7)], dim=1)  # Q x K x D
    scores = np.einsum("qkd,nd->qkn", candidates.numpy(), REFERENCE.numpy())
    best = scores.max(axis=1)
    relevance = relevances()["labels"]
    found = rank(candidates, REFERENCE, relevance, top=5, chunk_size=chunk)
    junk = {6, 11}
    for i in range(23):
        relevant = members(relevance.relevant, i)
        target = max(best[i, g] for g in relevant)
        assert found.ranks[i] == sum(1 for j in range(37) if j not in relevant | junk and best[i, j] > target)
        g_star = min(g for g in relevant if best[i, g] == target)
        assert found.best_candidate[i] == int(np.argmax(scores[i, :, g_star]))  # the first k on ties
        assert found.top_rows[i].tolist() == sorted(range(37), key=lambda j: (-best[i, j], j))[:5]


@pytest.mark.parametrize("q,n,chunk,budget", [(300, 300, 1024, 1 << 25), (1100, 1300, 1024, 1 << 25),
                                              (90, 700, 16, 16 * 50), (60, 90, 7, 7)])
def test_one_to_one_ranks_are_bit_identical_to_before(monkeypatch, q, n, chunk, budget):
    """The default run's figures: the scorer's one-to-one ranks equal the pre-scorer computation exactly, with
    duplicated references and queries equal to their positive (exact ties in float32)."""
    monkeypatch.setattr(scoring, "SCORE_BUDGET", budget)
    g = torch.Generator().manual_seed(q)
    reference = F.normalize(torch.randn(n, 16, generator=g), dim=1)
    reference[5::7] = reference[3]  # exact duplicates
    query = F.normalize(reference[:q] + 0.6 * torch.randn(q, 16, generator=g), dim=1)
    query[10::13] = reference[10:q:13]  # queries that are their own positive
    reference[11::17] = reference[12::17][: len(reference[11::17])]  # positives duplicated by a neighbour
    want = one_to_one_ranks_before(query, reference, chunk=chunk, budget=budget)
    got = ranks_of(query, reference, chunk_size=chunk)
    assert torch.equal(got, want)
    assert len(set(want.tolist())) > 10


def test_candidate_lists_follow_the_same_rule():
    """Top-k lists ranked by their returned scores equal the full ranking below k; a relevant reference not
    returned is rank k (no hit), unless its exact score is given, as the FAISS flat backend gives it."""
    relevance = relevances()["positives"]
    full = rank(QUERY, REFERENCE, relevance, hits=True)
    for k in (1, 4, 37):
        scores, rows = top_k(QUERY, REFERENCE, k)
        perm = torch.randperm(k, generator=torch.Generator().manual_seed(k))  # any order in, the rule's order out
        listed = rank_candidates(scores[:, perm], rows[:, perm], relevance, hits=True)
        assert torch.equal(listed.top_rows, rows)
        returned = (rows == relevance.relevant).any(dim=1)
        assert torch.equal(listed.ranks, torch.where(returned, full.ranks, torch.full_like(full.ranks, k)))
        exact = rank_candidates(scores, rows, relevance, hits=True,
                                target_scores=relevant_scores(QUERY, REFERENCE, relevance))
        assert torch.equal(exact.ranks, full.ranks.clamp(max=k))
        if k == 37:
            assert torch.equal(listed.hits, full.hits) and torch.equal(exact.hits, full.hits)
    labels = relevances()["labels"]
    scores, rows = top_k(QUERY, REFERENCE, 37)
    assert torch.equal(rank_candidates(scores, rows, labels).ranks, rank(QUERY, REFERENCE, labels).ranks)


def test_per_heading_lists_merge_into_the_max_over_headings():
    candidates = torch.stack([exact_rows(23, seed=s) for s in (5, 6, 7)], dim=1)  # Q x K x D
    scores = np.einsum("qkd,nd->qkn", candidates.numpy(), REFERENCE.numpy())
    k = 6
    lists = [top_k(candidates[:, h], REFERENCE, k) for h in range(3)]
    merged_scores, merged_rows, heading = merge_headings(torch.stack([s for s, _ in lists], dim=1),
                                                         torch.stack([r for _, r in lists], dim=1))
    full_scores, full_rows = top_k(candidates, REFERENCE, k)
    assert torch.equal(merged_rows[:, :k], full_rows) and torch.equal(merged_scores[:, :k], full_scores)
    for i in range(23):
        for m in range(k):
            row = int(merged_rows[i, m])
            assert int(heading[i, m]) == int(np.argmax(scores[i, :, row]))  # the first heading on ties


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="the relevance is for 23 queries and 37 references"):
        rank(QUERY[:5], REFERENCE, relevances()["one_to_one"])
    with pytest.raises(ValueError, match="query must be N x D or Q x K x D"):
        top_k(torch.ones(3), REFERENCE, 2)
    with pytest.raises(ValueError, match="k must be >= 1"):
        top_k(QUERY, REFERENCE, 0)
    with pytest.raises(ValueError, match="the hit rate needs semi-positives"):
        rank(QUERY, REFERENCE, relevances()["labels"], hits=True)
    with pytest.raises(ValueError, match="chunk_size must be >= 1"):
        rank(QUERY, REFERENCE, relevances()["labels"], chunk_size=-2)


def reference_recall(relevance: Relevance, k: int) -> float:
    """VPR-methods-evaluation's recall, rewritten: a query is found at K when one of its relevant references is among
    its K best (ties ordered in the query's favour), and the share is over every query, those with nothing
    relevant included."""
    found = 0
    for i in range(SCORES.shape[0]):
        relevant = members(relevance.relevant, i)
        ranking = sorted(range(SCORES.shape[1]), key=lambda j: (-SCORES[i, j], j not in relevant))
        found += any(j in relevant for j in ranking[:k])
    return found / SCORES.shape[0]


def test_a_query_with_nothing_relevant_is_a_miss_at_every_k_on_every_path():
    relevance = relevances()["radius_alone"]
    empty = ~relevance.has_relevant
    assert 0 < int(empty.sum()) < 23 and relevance.relevant.shape[1] > 1  # both kinds of query, several matches
    ks = (1, 5, 10, 37, 50)  # K = N and K > N: an empty row is still a miss
    full = rank(QUERY, REFERENCE, relevance, every_relevant=True)
    want = {f"R@{k}": reference_recall(relevance, k) for k in ks} | {"R@1%": reference_recall(relevance, 1)}
    assert recall_summary(full.ranks, ks, 37) == pytest.approx(want, abs=1e-12)
    assert want["R@50"] == pytest.approx(1 - float(empty.double().mean()))
    for k in (1, 4, 37):  # candidate lists: with the exact targets (the FAISS flat backend's), and whole lists
        scores, rows = top_k(QUERY, REFERENCE, k)
        for targets in (None, relevant_scores(QUERY, REFERENCE, relevance)):
            listed = rank_candidates(scores, rows, relevance, target_scores=targets)
            assert (listed.ranks[empty] == scoring.NO_RELEVANT).all()
            if targets is not None or k == 37:  # a shorter list alone misses a relevant one tied at its end
                assert recall_summary(listed.ranks, (k,), 37)[f"R@{k}"] == pytest.approx(reference_recall(relevance, k))
    kept = average_precision(full.relevant_ranks[~empty])["AP"]  # AP: an empty row scores 0 and counts
    assert average_precision(full.relevant_ranks)["AP"] == pytest.approx(kept * int((~empty).sum()) / 23)
    semi = replace(relevance, semi_positives=torch.full((23, 1), 3))  # the hit rate: never a hit
    assert not rank(QUERY, REFERENCE, semi, hits=True).hits[empty].any()
    assert not rank_candidates(*top_k(QUERY, REFERENCE, 37), semi, hits=True).hits[empty].any()


def test_a_query_with_nothing_relevant_has_no_heading():
    candidates = torch.stack([exact_rows(23, seed=s) for s in (5, 6, 7)], dim=1)  # Q x K x D, headings 0/120/240
    scores = np.einsum("qkd,nd->qkn", candidates.numpy(), REFERENCE.numpy())
    relevance = relevances()["radius_alone"]
    found = rank(candidates, REFERENCE, relevance)
    truth = np.random.default_rng(0).uniform(0, 360, 23)
    errors = []
    for i in range(23):
        relevant = members(relevance.relevant, i)
        if not relevant:
            assert found.best_candidate[i] == -1
            continue
        g_star = min(relevant, key=lambda g: (-scores[i, :, g].max(), g))
        errors.append(circular_error_deg(120.0 * np.argmax(scores[i, :, g_star]), truth[i]))
    metrics = heading_metrics(candidates, REFERENCE, truth, relevance=relevance)
    assert metrics["heading_mean_deg"] == pytest.approx(np.mean(errors))
    assert metrics["heading_median_deg"] == pytest.approx(np.median(errors))
    nothing = Relevance.within_radius(None, np.zeros((23, 2)), np.full((37, 2), 100.0), "xy", 25.0)
    assert nothing.relevant.shape == (23, 1) and not nothing.has_relevant.any()
    worst = heading_metrics(candidates, REFERENCE, truth, relevance=nothing)
    assert worst["R@1"] == 0.0 and worst["heading_mean_deg"] == 180.0
