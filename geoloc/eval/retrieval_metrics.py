"""Every retrieval metric a split supports, from one call: recall, VIGOR's hit rate and metres, University-1652's AP.

Which keys appear (all Python floats, JSON-ready):

- always: ``R@K`` for K in ks and ``R@1%``. Without labels they are `recall_at_k`'s (the rank of the positive,
  VIGOR / SAFA convention);
- with ``semi_positives``: ``hit_rate``, the share of queries whose top-1 is the positive or a semi-positive (VIGOR);
- with ``query_labels`` and ``reference_labels``: ``AP``, and the R@ keys follow the label rule, "a reference of
  the query's label in the top K" (University-1652, `mean_average_precision`);
- with ``query_latlon`` and ``reference_latlon``: ``median_m``, ``within_10m``, ``within_25m``, ``within_50m``, the
  metres from each query to its top-1 reference's centre (`geo_error`).

With labels, the positives rule can give a lower R@1 than the benchmark's (the positive is one image of the
building; any image of it counts there), so one result never mixes the two: with labels every R@ key is the
label rule, the positives are only checked to carry their query's label, and semi-positives are refused (no
dataset has both; a hit rate beside label recall would be a third rule).
"""
from __future__ import annotations

from typing import Iterable

from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.average_precision import check_ks, label_tensor, mean_average_precision
from geoloc.eval.gallery import as_float_tensor
from geoloc.eval.geo_error import latlon_array, metre_errors, metre_summary, top1_indices
from geoloc.eval.recall import _check_pair, _index_tensor, recall_at_k

__all__ = ["retrieval_metrics", "split_metrics"]


def _check_labelled_positives(positives, query_labels, reference_labels) -> None:
    pos = _index_tensor(positives, "positives", tuple(query_labels.shape), reference_labels.shape[0],
                        allow_none=False)
    wrong = reference_labels[pos] != query_labels
    if wrong.any():
        i = int(wrong.nonzero()[0])
        raise ValueError(f"positives of query {i} is reference {int(pos[i])} with label "
                         f"{int(reference_labels[pos[i]])}, but the query's label is {int(query_labels[i])} "
                         f"({int(wrong.sum())} such queries): positives and labels disagree")


def _pair(a, b, name_a: str, name_b: str) -> bool:
    if (a is None) != (b is None):
        given, missing = (name_a, name_b) if b is None else (name_b, name_a)
        raise ValueError(f"{given} was given without {missing}: give both or neither")
    return a is not None


def retrieval_metrics(query, reference, positives=None, semi_positives=None, query_latlon=None,
                      reference_latlon=None, query_labels=None, reference_labels=None,
                      ks: Iterable[int] = (1, 5, 10)) -> dict[str, float]:
    """The metrics of the module table for query Q x D and reference N x D descriptors (tensors or numpy).

    positives (Q,) int (default: query i matches reference i); semi_positives (Q, S) int, -1 for none;
    query_latlon (Q, 2), reference_latlon (N, 2) degrees; query_labels (Q,), reference_labels (N,) int, -1 = junk
    reference. Descriptors are L2-normalised and checked as in `recall_at_k`. Errors name the argument at fault.
    """
    ks = check_ks(ks)
    labelled = _pair(query_labels, reference_labels, "query_labels", "reference_labels")
    located = _pair(query_latlon, reference_latlon, "query_latlon", "reference_latlon")
    q, r = _check_pair(query, reference, one_to_one=positives is None and not labelled)
    if labelled:
        if semi_positives is not None:
            raise ValueError("semi_positives and labels were both given: with labels the R@ keys count any "
                             "reference of the query's label, so a semi-positive hit rate would mix two rules; "
                             "pass one or the other")
        q_labels = label_tensor(query_labels, "query_labels", q.shape[0])
        r_labels = label_tensor(reference_labels, "reference_labels", r.shape[0])
        if positives is not None:
            _check_labelled_positives(positives, q_labels, r_labels)
        scores = mean_average_precision(q, r, q_labels, r_labels, ks)
        out = {key: value for key, value in scores.items() if key != "AP"}
        out["AP"] = scores["AP"]
    else:
        out = recall_at_k(q, r, ks, positives=positives, semi_positives=semi_positives)
    if located:
        query_latlon = latlon_array(query_latlon, "query_latlon", q.shape[0])
        reference_latlon = latlon_array(reference_latlon, "reference_latlon", r.shape[0])
        out.update(metre_summary(metre_errors(top1_indices(q, r), query_latlon, reference_latlon)))
    return out


def split_metrics(query, reference, split: RetrievalSplit, ks: Iterable[int] = (1, 5, 10)) -> dict[str, float]:
    """`retrieval_metrics` with the positives, semi-positives, GPS and labels of ``split``; query / reference rows
    must be in the split's query / reference order."""
    for name, x, rows in (("query", query, split.num_queries), ("reference", reference, split.num_references)):
        if as_float_tensor(x, name).shape[0] != rows:
            raise ValueError(f"{name} has {x.shape[0]} rows but split {split.name!r} has {rows} {name} images: "
                             "describe every image of the split, in its order")
    return retrieval_metrics(query, reference, split.positives, split.semi_positives, split.query_latlon,
                             split.reference_latlon, split.query_labels, split.reference_labels, ks)


def collapsed_split_metrics(split: RetrievalSplit, ks: Iterable[int] = (1, 5, 10)) -> dict[str, float]:
    """What `split_metrics` reports when the gallery has collapsed onto one point (geoloc.eval.descriptors): every
    query would "find" its place through ties, so each score is its worst value rather than a perfect one."""
    out = {**{f"R@{k}": 0.0 for k in ks}, "R@1%": 0.0}
    if split.semi_positives is not None:
        out["hit_rate"] = 0.0
    if split.query_labels is not None:
        out["AP"] = 0.0
    if split.query_latlon is not None and split.reference_latlon is not None:
        out.update({"median_m": float("inf"), "within_10m": 0.0, "within_25m": 0.0, "within_50m": 0.0})
    return out
