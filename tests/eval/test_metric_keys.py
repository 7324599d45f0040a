"""Each metric declares its keys once (geoloc/eval/keys.py); a run's collapsed result is derived from the key sets it
reports, so for every kind of split the computed keys and the collapsed keys are the same, in the same order."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from geoloc.data.geo import offset_to_latlon
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval import GalleryIndex
from geoloc.eval.keys import KeySet, collapsed, guarded
from geoloc.eval.retrieval_metrics import index_metrics, split_metrics, split_plan
from geoloc.tasks.crossview.heading import heading_metrics, heading_plan

from helpers.descriptor_data import labelled_data, vigor_like_data
from helpers.vpr_reference import reference_recalls


def splits() -> dict[str, tuple[RetrievalSplit, torch.Tensor, torch.Tensor]]:
    """(split, query, reference descriptors) of every kind of split."""
    g = torch.Generator().manual_seed(0)
    pairs_ref = F.normalize(torch.randn(20, 8, generator=g), dim=1)
    pairs_query = F.normalize(pairs_ref + 0.5 * torch.randn(20, 8, generator=g), dim=1)
    query, reference, positives, semi = vigor_like_data(12, 30)
    latlon = [offset_to_latlon((40.7, -74.0), 30.0 * np.arange(n) % 300, 30.0 * (np.arange(n) // 10))
              for n in (12, 30)]
    lq, lr, ql, rl = labelled_data(n_query=15, n_junk=0)
    first = np.array([int(torch.nonzero(rl == label)[0]) for label in ql])
    names = lambda n, p: [f"{p}{i}" for i in range(n)]  # noqa: E731
    xy = np.stack([np.arange(20.0) * 10, np.zeros(20)], axis=1)
    return {
        "one_to_one": (RetrievalSplit("pairs", "/d", names(20, "q"), names(20, "r"), np.arange(20),
                                      query_xy=xy, reference_xy=xy), pairs_query, pairs_ref),
        "vigor": (RetrievalSplit("vigor", "/d", names(12, "q"), names(30, "r"), positives.numpy(), semi.numpy(),
                                 *latlon), query.float(), reference.float()),
        "labels": (RetrievalSplit("u1652", "/d", names(15, "q"), names(len(rl), "r"), first,
                                  query_labels=ql.numpy(), reference_labels=rl.numpy()), lq.float(), lr.float()),
        "radius": (RetrievalSplit("vpr", "/d", names(20, "q"), names(20, "r"), np.arange(20) // 2 * 2,
                                  query_xy=xy, reference_xy=xy + 3.0, relevance_radius_m=25.0),
                   pairs_query, pairs_ref),
        # the radius alone: the queries past 215 m east have no reference within 25 m
        "radius_alone": (RetrievalSplit("own", "/d", names(20, "q"), names(20, "r"), np.minimum(np.arange(20) * 3, 19),
                                        query_xy=xy * 3, reference_xy=xy + [0.0, 3.0], relevance_radius_m=25.0,
                                        radius_alone=True), pairs_query, pairs_ref),
    }


EXPECTED = {
    "one_to_one": ["R@1", "R@5", "R@10", "R@1%"],
    "vigor": ["R@1", "R@5", "R@10", "R@1%", "hit_rate", "median_m", "within_10m", "within_25m", "within_50m"],
    "labels": ["R@1", "R@5", "R@10", "R@1%", "AP"],
    "radius": ["R@1", "R@5", "R@10", "R@1%", "median_m", "within_10m", "within_25m", "within_50m"],
    "radius_alone": ["R@1", "R@5", "R@10", "R@1%", "median_m", "within_10m", "within_25m", "within_50m"],
}


@pytest.mark.parametrize("kind", list(EXPECTED))
def test_computed_and_collapsed_results_hold_the_declared_keys(kind):
    split, query, reference = splits()[kind]
    plan = split_plan(split)
    worst = collapsed(plan)
    assert list(worst) == EXPECTED[kind]
    assert list(split_metrics(query, reference, split)) == EXPECTED[kind]
    assert worst["R@1"] == 0.0 and all(v == 0.0 for k, v in worst.items() if k != "median_m")
    if "median_m" in worst:
        assert worst["median_m"] == math.inf
    with pytest.warns(UserWarning, match="collapsed"):
        reported = guarded(lambda: pytest.fail("a collapse is not scored"), 0.0, plan)
    assert reported == {**worst, "reference_spread": 0.0}


@pytest.mark.parametrize("kind", list(EXPECTED))
@pytest.mark.parametrize("index_kind", ["flat", "hnsw"])
def test_a_gallery_index_reports_its_plan(kind, index_kind):
    """A flat index is scored exactly (AP included); an approximate one from its top-k lists, without AP."""
    if index_kind != "flat":
        pytest.importorskip("faiss")
    split, query, reference = splits()[kind]
    index = GalleryIndex(reference.shape[1], backend="torch" if index_kind == "flat" else "faiss",
                         kind=index_kind).add(reference)
    got = index_metrics(index, query, split)
    plan = split_plan(split, exact=index_kind == "flat")
    assert list(got) == list(collapsed(plan))
    assert ("AP" in got) == (kind == "labels" and index_kind == "flat")
    if index_kind == "flat":
        assert got == split_metrics(query, reference, split)


@pytest.mark.parametrize("index_kind", ["flat", "hnsw"])
def test_a_gallery_counts_a_query_with_nothing_relevant_as_a_miss(index_kind):
    """The saved-gallery path against VPR-methods-evaluation's recall (helpers/vpr_reference.py), exact or from an
    approximate index's top-k lists."""
    if index_kind != "flat":
        pytest.importorskip("faiss")
    split, query, reference = splits()["radius_alone"]
    relevant = [{int(j) for j in row if j >= 0} for row in split.relevance.relevant]
    assert 0 < sum(not r for r in relevant) < 20  # both kinds of query
    index = GalleryIndex(reference.shape[1], backend="torch" if index_kind == "flat" else "faiss",
                         kind=index_kind).add(reference)
    ks = (1, 5, 10, 20)
    want = reference_recalls(query.numpy(), reference.numpy(), relevant, ks)
    got = index_metrics(index, query, split, ks)
    assert {k: got[k] for k in want} == pytest.approx(want, abs=1e-12)
    assert want["R@20"] == pytest.approx(np.mean([bool(r) for r in relevant]))


def test_the_heading_search_declares_its_keys():
    g = torch.Generator().manual_seed(1)
    query, reference = F.normalize(torch.randn(6, 4, 8, generator=g), dim=2), F.normalize(torch.randn(6, 8), dim=1)
    got = heading_metrics(query, reference, torch.zeros(6))
    assert list(got) == list(collapsed(heading_plan()))
    assert collapsed(heading_plan())["heading_median_deg"] == 180.0


def test_a_metric_that_drifts_from_its_declaration_is_an_error():
    keys = KeySet({"R@1": 0.0, "R@1%": 0.0})
    assert keys.values({"R@1%": np.float64(0.5), "R@1": torch.tensor(0.25)}) == {"R@1": 0.25, "R@1%": 0.5}
    with pytest.raises(RuntimeError, match="declares"):
        keys.values({"R@1": 0.5})
    with pytest.raises(RuntimeError, match="declares"):
        guarded(lambda: {"R@1": 0.5, "R@1%": 0.5, "AP": 0.1}, 1.0, [keys])
