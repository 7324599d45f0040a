"""Every retrieval metric a split supports, from one pass of the scorer: recall, VIGOR's hit rate and metres,
University-1652's AP.

The plan (`metric_plan`) is the list of key sets a run reports, read from the relevance and the positions:

- always: ``R@K`` for K in ks and ``R@1%``: the rank of the best relevant reference (`geoloc.eval.scoring`): the
  positive (SAFA / VIGOR convention), any image of the query's building with labels (University-1652), any
  reference within the radius (VPR);
- with semi-positives: ``hit_rate``, VIGOR's code rule (no reference outside the positive and its semi-positives
  strictly closer than the positive);
- with labels, scored exactly: ``AP`` (University-1652, `average_precision.py`); a candidate list (an approximate
  gallery) does not rank the whole gallery, so it has no AP;
- with positions: ``median_m``, ``within_10m``, ``within_25m``, ``within_50m``: the metres from each query to its
  top-1 reference's centre (`geo_error`). Splits report them beyond one-to-one data only, where retrieving another
  reference than the query's own is a position error, not a wrong pair.

The "collapsed" result of a run is `geoloc.eval.keys.collapsed` of its plan. One relevance is used throughout, so
one result never mixes rules: with labels every R@ key is label recall, and semi-positives beside labels are
refused.
"""
from __future__ import annotations

from typing import Iterable

import torch

from geoloc.data.relevance import Relevance, index_tensor, label_tensor
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.average_precision import AP_KEYS, average_precision
from geoloc.eval.candidates import rank_candidates
from geoloc.eval.descriptors import as_float_tensor, checked_pair
from geoloc.eval.search_index import GalleryIndex
from geoloc.eval.geo_error import METRE_KEYS, latlon_array, metre_errors, metre_summary
from geoloc.eval.keys import KeySet, collapsed
from geoloc.eval.recall import HIT_RATE_KEYS, check_ks, hit_rate, one_percent_k, recall_keys, recall_summary
from geoloc.eval.scoring import Ranking, rank

__all__ = ["index_metrics", "metric_plan", "retrieval_metrics", "scored_metrics", "split_metrics", "split_plan",
           "scored_positions"]

Positions = tuple  # (kind "latlon" | "xy", query (Q, 2), reference (N, 2))


def metric_plan(relevance: Relevance, ks: Iterable[int], located: bool, exact: bool = True) -> list[KeySet]:
    """The key sets reported for this relevance: recall, then hit rate, AP, metres where they apply."""
    plan = [recall_keys(check_ks(ks))]
    if relevance.semi_positives is not None:
        plan.append(HIT_RATE_KEYS)
    if relevance.kind == "labels" and exact:
        plan.append(AP_KEYS)
    if located:
        plan.append(METRE_KEYS)
    return plan


def _summaries(found: Ranking, plan: list[KeySet], ks, num_references: int, positions: Positions | None) -> dict:
    out = recall_summary(found.ranks, ks, num_references)
    if HIT_RATE_KEYS in plan:
        out.update(hit_rate(found.hits))
    if AP_KEYS in plan:
        out.update(average_precision(found.relevant_ranks))
    if METRE_KEYS in plan:
        kind, query_positions, reference_positions = positions
        out.update(metre_summary(metre_errors(found.top_rows[:, 0], query_positions, reference_positions, kind)))
    if list(out) != list(collapsed(plan)):
        raise RuntimeError(f"computed {list(out)} but the plan declares {list(collapsed(plan))}")
    return out


def scored_metrics(query, reference, relevance: Relevance, ks: Iterable[int] = (1, 5, 10),
                   positions: Positions | None = None) -> dict[str, float]:
    """The plan's metrics of Q x D query and N x D reference descriptors, from one pass of the scorer."""
    ks = check_ks(ks)
    plan = metric_plan(relevance, ks, positions is not None)
    found = rank(query, reference, relevance, hits=HIT_RATE_KEYS in plan, every_relevant=AP_KEYS in plan,
                 top=1 if positions is not None else 0)
    return _summaries(found, plan, ks, relevance.num_references, positions)


def _pair(a, b, name_a: str, name_b: str) -> bool:
    if (a is None) != (b is None):
        given, missing = (name_a, name_b) if b is None else (name_b, name_a)
        raise ValueError(f"{given} was given without {missing}: give both or neither")
    return a is not None


def _check_labelled_positives(positives, query_labels, reference_labels) -> None:
    pos = index_tensor(positives, "positives", tuple(query_labels.shape), reference_labels.shape[0],
                       allow_none=False)
    wrong = reference_labels[pos] != query_labels
    if wrong.any():
        i = int(wrong.nonzero()[0])
        raise ValueError(f"positives of query {i} is reference {int(pos[i])} with label "
                         f"{int(reference_labels[pos[i]])}, but the query's label is {int(query_labels[i])} "
                         f"({int(wrong.sum())} such queries): positives and labels disagree")


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
    q, r = checked_pair(query, reference, one_to_one=positives is None and not labelled)
    n_query, n_ref = q.shape[0], r.shape[0]
    if labelled:
        if semi_positives is not None:
            raise ValueError("semi_positives and labels were both given: with labels the R@ keys count any "
                             "reference of the query's label, so a semi-positive hit rate would mix two rules; "
                             "pass one or the other")
        q_labels = label_tensor(query_labels, "query_labels", n_query)
        r_labels = label_tensor(reference_labels, "reference_labels", n_ref)
        if positives is not None:
            _check_labelled_positives(positives, q_labels, r_labels)
        relevance = Relevance.from_labels(q_labels, r_labels)
    elif positives is None and semi_positives is None:
        relevance = Relevance.one_to_one(n_query, n_ref)
    else:
        positives = torch.arange(n_query) if positives is None else positives
        relevance = Relevance.from_positives(positives, n_ref, semi_positives, num_queries=n_query)
    positions = None
    if located:
        positions = ("latlon", latlon_array(query_latlon, "query_latlon", n_query),
                     latlon_array(reference_latlon, "reference_latlon", n_ref))
    return scored_metrics(q, r, relevance, ks, positions)


def scored_positions(split: RetrievalSplit) -> Positions | None:
    """(kind, query, reference positions) that the metre keys score, or None: one-to-one splits and splits
    without positions have none."""
    kind, query_positions, reference_positions = split.positions()
    if kind is None or split.one_to_one:
        return None
    return kind, query_positions, reference_positions


def split_plan(split: RetrievalSplit, ks: Iterable[int] = (1, 5, 10), exact: bool = True) -> list[KeySet]:
    """The key sets a split is scored with (`metric_plan`): its collapsed result is `keys.collapsed` of it."""
    return metric_plan(split.relevance, ks, scored_positions(split) is not None, exact)


def _check_rows(split: RetrievalSplit, **descriptors) -> None:
    for name, x in descriptors.items():
        rows = {"query": split.num_queries, "reference": split.num_references}[name]
        got = as_float_tensor(x, name, ndims=(2, 3)).shape[0]
        if got != rows:
            raise ValueError(f"{name} has {got} rows but split {split.name!r} has {rows} {name} images: describe "
                             "every image of the split, in its order")


def split_metrics(query, reference, split: RetrievalSplit, ks: Iterable[int] = (1, 5, 10)) -> dict[str, float]:
    """`scored_metrics` with the relevance and positions of ``split``; query / reference rows must be in the
    split's query / reference order."""
    _check_rows(split, query=query, reference=reference)
    return scored_metrics(query, reference, split.relevance, ks, scored_positions(split))


def index_metrics(index: GalleryIndex, query, split: RetrievalSplit, ks: Iterable[int] = (1, 5, 10)) -> dict:
    """What a gallery index scores of a split whose reference j is gallery row j.

    A flat (exact) index is scored from its stored vectors by `split_metrics`: the same numbers as the exact
    path, AP included. Approximate kinds are scored from their top-k lists (`geoloc.eval.candidates`), k = the
    largest K asked (or of R@1%), without AP."""
    ks = check_ks(ks)
    if len(index) != split.num_references:
        raise ValueError(f"the gallery index holds {len(index)} references but split {split.name!r} has "
                         f"{split.num_references}")
    if index.kind == "flat":
        return split_metrics(query, index.vectors(), split, ks)
    _check_rows(split, query=query)
    relevance, positions = split.relevance, scored_positions(split)
    plan = metric_plan(relevance, ks, positions is not None, exact=False)
    scores, rows = index.search(query, max(*ks, one_percent_k(len(index))))
    found = rank_candidates(scores, rows, relevance, hits=HIT_RATE_KEYS in plan)
    return _summaries(found, plan, ks, len(index), positions)
