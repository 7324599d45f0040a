"""Relevance is a property of the split (RetrievalSplit.relevance, geoloc/data/relevance.py): which references each
kind of split makes relevant, and the errors of bad relevance inputs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from geoloc.data.geo import offset_to_latlon
from geoloc.data.relevance import RADIUS_M, Relevance
from geoloc.data.retrieval_split import RetrievalSplit


def split(n_query=4, n_ref=6, **kw) -> RetrievalSplit:
    kw.setdefault("positives", np.arange(n_query) % n_ref)
    return RetrievalSplit("s", "/data", [f"q{i}" for i in range(n_query)], [f"r{j}" for j in range(n_ref)], **kw)


def rows(relevance: Relevance) -> list[list[int]]:
    return [[int(j) for j in row if j >= 0] for row in relevance.relevant]


def test_each_kind_of_split_says_what_is_relevant():
    assert split(4, 4).relevance.kind == "one_to_one" and rows(split(4, 4).relevance) == [[0], [1], [2], [3]]
    vigor = split(positives=np.array([5, 0, 2, 2]), semi_positives=np.array([[1, -1], [-1, -1], [3, 4], [0, -1]]))
    assert vigor.relevance.kind == "positives" and rows(vigor.relevance) == [[5], [0], [2], [2]]
    assert vigor.relevance.semi_positives.tolist() == [[1, -1], [-1, -1], [3, 4], [0, -1]]  # for the hit rate only
    hit = vigor.relevance.hit()
    assert rows(hit) == rows(vigor.relevance) and hit.ignored.tolist() == vigor.semi_positives.tolist()
    # University-1652 satellite -> drone: every drone image of the query's building, junk (-1) never
    u1652 = split(2, 7, positives=np.array([1, 0]), query_labels=np.array([9, 4]),
                  reference_labels=np.array([4, 9, 4, -1, 9, 9, 4]), query_view="aerial")
    assert u1652.relevance.kind == "labels" and rows(u1652.relevance) == [[1, 4, 5], [0, 2, 6]]
    assert u1652.relevance.ignored_references.tolist() == [False, False, False, True, False, False, False]


@pytest.mark.parametrize("kind", ["xy", "latlon"])
def test_the_radius_kind_takes_the_positive_and_every_reference_within_it(kind):
    reference_xy = np.array([[0.0, 0.0], [20.0, 0.0], [24.5, 0.0], [26.0, 0.0], [0.0, 100.0]])
    query_xy = np.array([[0.0, 0.0], [0.0, 90.0]])
    positions = {"xy": dict(query_xy=query_xy, reference_xy=reference_xy),
                 "latlon": dict(query_latlon=offset_to_latlon((47.6, -122.3), *query_xy.T),
                                reference_latlon=offset_to_latlon((47.6, -122.3), *reference_xy.T))}[kind]
    vpr = split(2, 5, positives=np.array([3, 4]), relevance_radius_m=25.0, **positions)
    assert vpr.relevance.kind == "radius" and not vpr.one_to_one
    # query 0: the references 0, 20 and 24.5 m away, and its positive at 26 m; query 1: its positive only
    assert rows(vpr.relevance) == [[0, 1, 2, 3], [4]]
    assert RADIUS_M == 25.0
    on_the_edge = split(1, 2, positives=np.array([0]), relevance_radius_m=25.0, query_xy=np.zeros((1, 2)),
                        reference_xy=np.array([[0.0, 0.0], [15.0, 20.0]]))
    assert rows(on_the_edge.relevance) == [[0, 1]]  # exactly 25 m counts
    alone = split(2, 5, positives=np.array([3, 4]), relevance_radius_m=25.0, radius_alone=True, **positions)
    assert alone.relevance.kind == "radius" and rows(alone.relevance) == [[0, 1, 2], [4]]  # not the positive at 26 m
    far = split(2, 2, positives=np.array([0, 1]), relevance_radius_m=25.0, radius_alone=True,
                query_xy=np.array([[0.0, 0.0], [0.0, 60.0]]), reference_xy=np.array([[0.0, 25.0], [0.0, 25.1]]))
    assert rows(far.relevance) == [[0], []] and far.relevance.has_relevant.tolist() == [True, False]


@pytest.mark.parametrize("kw,match", [
    (dict(relevance_radius_m=25.0), "needs query and reference positions"),
    (dict(relevance_radius_m=-1.0, query_xy=np.zeros((4, 2)), reference_xy=np.zeros((6, 2))), "radius >= 0"),
    (dict(relevance_radius_m=25.0, query_xy=np.zeros((4, 2)), reference_xy=np.zeros((6, 2)),
          query_labels=np.zeros(4, int), reference_labels=np.zeros(6, int)), "labels or relevance_radius_m"),
    (dict(radius_alone=True), "radius_alone needs relevance_radius_m"),
])
def test_a_bad_radius_is_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        split(**kw)


def test_bad_relevance_inputs_name_what_is_wrong():
    with pytest.raises(ValueError, match="query 1 has label 7, which no reference has"):
        Relevance.from_labels([3, 7], [3, 3, -1])
    with pytest.raises(ValueError, match="query 0 has label -1.*junk"):
        Relevance.from_labels([-1], [3, -1])
    with pytest.raises(TypeError, match="query_labels must hold integer labels"):
        Relevance.from_labels([3.0], [3])
    with pytest.raises(ValueError, match=r"positives of query 1 is 6: indices must lie in \[0, 6\)"):
        Relevance.from_positives([0, 6], 6)
    with pytest.raises(ValueError, match=r"semi_positives must be \(Q, S\) = \(2, S\)"):
        Relevance.from_positives([0, 1], 6, semi_positives=[0, 1])
    with pytest.raises(ValueError, match="got 3 queries and only 2 references"):
        Relevance.one_to_one(3, 2)
    with pytest.raises(ValueError, match="the hit rate needs semi-positives"):
        Relevance.from_positives([0], 2).hit()
    assert Relevance.from_labels(torch.tensor([5]), np.array([5, 5, 1])).relevant.tolist() == [[0, 1]]
