"""retrieval_metrics / split_metrics: which keys appear when, that each equals its own metric, and bad input."""
import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from geoloc.data.geo import offset_to_latlon
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.average_precision import mean_average_precision
from geoloc.eval.geo_error import metre_errors, metre_summary
from geoloc.eval.scoring import top_k
from geoloc.eval.recall import recall_at_k
from geoloc.eval.retrieval_metrics import retrieval_metrics, split_metrics

from helpers.descriptor_data import labelled_data, vigor_like_data

METRE_KEYS = {"median_m", "within_10m", "within_25m", "within_50m"}


def one_to_one(q=30, n=80, seed=0):
    g = torch.Generator().manual_seed(seed)
    reference = F.normalize(torch.randn(n, 8, generator=g), dim=1)
    query = F.normalize(reference[:q] + 0.4 * torch.randn(q, 8, generator=g), dim=1)
    return query, reference


def located(query, reference, seed=0):
    """GPS for every image: references on a grid 30 m apart, queries a few metres from their positive."""
    rng = np.random.default_rng(seed)
    n = len(reference)
    reference_latlon = offset_to_latlon((40.7, -74.0), 30.0 * (np.arange(n) % 10), 30.0 * (np.arange(n) // 10))
    query_latlon = offset_to_latlon((40.7, -74.0), 30.0 * (np.arange(len(query)) % 10) + rng.uniform(0, 20, len(query)),
                                    30.0 * (np.arange(len(query)) // 10))
    return query_latlon, reference_latlon


def test_one_to_one_is_recall_at_k_exactly():
    query, reference = one_to_one()
    got = retrieval_metrics(query, reference, ks=(1, 5))
    assert got == recall_at_k(query, reference, ks=(1, 5))
    assert 0 < got["R@1"] < 1 and set(got) == {"R@1", "R@5", "R@1%"}


def test_semi_positives_add_the_hit_rate():
    query, reference, positives, semi = vigor_like_data(40, 120)
    got = retrieval_metrics(query, reference, positives, semi)
    assert got == recall_at_k(query, reference, positives=positives, semi_positives=semi)
    assert got["R@1"] < got["hit_rate"]


def test_labels_give_ap_and_label_recall_only():
    query, reference, ql, rl = labelled_data(n_junk=0)
    positives = torch.tensor([int(torch.nonzero(rl == label)[0]) for label in ql])  # first of the building
    got = retrieval_metrics(query, reference, positives, query_labels=ql, reference_labels=rl)
    assert got == mean_average_precision(query, reference, ql, rl, ks=(1, 5, 10))
    assert list(got) == ["R@1", "R@5", "R@10", "R@1%", "AP"]
    # the data tell the two rules apart: the positive alone is on top less often than any of its building
    assert recall_at_k(query, reference, positives=positives)["R@1"] < got["R@1"]


def test_gps_adds_the_metre_summary_of_the_top1():
    query, reference = one_to_one()
    query_latlon, reference_latlon = located(query, reference)
    got = retrieval_metrics(query, reference, query_latlon=query_latlon, reference_latlon=reference_latlon)
    errors = metre_errors(top_k(query, reference, 1)[1][:, 0], query_latlon, reference_latlon)
    assert {k: got[k] for k in METRE_KEYS} == metre_summary(errors)
    assert set(got) == {"R@1", "R@5", "R@10", "R@1%"} | METRE_KEYS
    assert 0 < got["within_10m"] < got["within_50m"] < 1  # some top-1 right (under 20 m), some wrong


def test_hand_metres_follow_the_top1():
    # query 0 retrieves reference 1 (40 m from it), query 1 its own reference 1 (5 m)
    query = torch.tensor([[0.0, 1.0], [0.0, 1.0]])
    reference = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    reference_latlon = offset_to_latlon((47.6, -122.3), [0.0, 40.0], [0.0, 0.0])
    query_latlon = offset_to_latlon((47.6, -122.3), [0.0, 45.0], [0.0, 0.0])
    got = retrieval_metrics(query, reference, [0, 1], query_latlon=query_latlon, reference_latlon=reference_latlon)
    assert got["R@1"] == 0.5 and got["median_m"] == pytest.approx(22.5, abs=0.01)
    assert (got["within_10m"], got["within_25m"], got["within_50m"]) == (0.5, 0.5, 1.0)


def test_values_are_plain_floats():
    query, reference, ql, rl = labelled_data(n_query=20)
    query_latlon, reference_latlon = located(query, reference)
    got = retrieval_metrics(query.numpy(), reference.numpy(), None, None, query_latlon, reference_latlon, ql, rl)
    assert all(type(v) is float for v in got.values()) and json.loads(json.dumps(got)) == got
    assert {"AP"} | METRE_KEYS <= set(got)


def test_split_metrics_reads_the_split():
    query, reference, positives, semi = vigor_like_data(12, 30)
    query_latlon, reference_latlon = located(query, reference)
    split = RetrievalSplit("vigor/test", "/data", [f"q{i}.jpg" for i in range(12)],
                           [f"r{j}.png" for j in range(30)], positives.numpy(), semi.numpy(), query_latlon,
                           reference_latlon)
    assert split_metrics(query, reference, split, ks=(1, 3)) == retrieval_metrics(
        query, reference, positives, semi, query_latlon, reference_latlon, ks=(1, 3))
    assert {"hit_rate"} | METRE_KEYS <= set(split_metrics(query, reference, split))
    with pytest.raises(ValueError, match="query has 11 rows but split 'vigor/test' has 12 query images"):
        split_metrics(query[:11], reference, split)
    with pytest.raises(ValueError, match="reference has 29 rows .* 30 reference images"):
        split_metrics(query, reference[:29], split)


def test_split_metrics_with_labels_is_the_benchmark():
    query, reference, ql, rl = labelled_data(n_query=15, n_junk=0)
    positives = np.array([int(torch.nonzero(rl == label)[0]) for label in ql])
    split = RetrievalSplit("u1652/test", "/data", [f"q{i}" for i in range(15)], [f"r{j}" for j in range(len(rl))],
                           positives, query_labels=ql.numpy(), reference_labels=rl.numpy())
    assert split_metrics(query, reference, split) == mean_average_precision(query, reference, ql, rl, (1, 5, 10))


@pytest.mark.parametrize("kwargs,match", [
    (dict(query=torch.ones(3, 5)), "dimensions differ"),
    (dict(positives=[0, 1]), "positives must have shape"),
    (dict(positives=[0, 1, 2], semi_positives=[[0], [1]]), "semi_positives must be"),
    (dict(query_latlon=np.zeros((2, 2)), reference_latlon=np.zeros((4, 2))), r"query_latlon must be \(3, 2\)"),
    (dict(query_latlon=np.zeros((3, 2)), reference_latlon=np.zeros((3, 2))), r"reference_latlon must be \(4, 2\)"),
    (dict(query_latlon=np.zeros((3, 2))), "query_latlon was given without reference_latlon"),
    (dict(reference_labels=[0, 1, 2, 3]), "reference_labels was given without query_labels"),
    (dict(query_labels=[0, 1], reference_labels=[0, 1, 2, 3]), r"query_labels must have shape \(3,\)"),
    (dict(query_labels=[0, 1, 2], reference_labels=[0, 1, 2]), r"reference_labels must have shape \(4,\)"),
    (dict(query_labels=[0, 1, 2], reference_labels=[0, 1, 2, 2], semi_positives=[[3], [3], [3]]),
     "semi_positives and labels"),
    (dict(positives=[0, 1, 3], query_labels=[0, 1, 2], reference_labels=[0, 1, 2, 3]),
     "positives of query 2 is reference 3 with label 3, but the query's label is 2"),
    (dict(ks=()), "ks must be"),
])
def test_bad_input_names_the_argument(kwargs, match):
    args = dict(query=torch.eye(4)[:3], reference=torch.eye(4)) | kwargs
    with pytest.raises(ValueError, match=match):
        retrieval_metrics(**args)
