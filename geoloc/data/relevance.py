"""Which references are relevant to each query: the one definition every metric path ranks by.

The rules: docs/conventions.md "Relevance" and "Ranks and Recall@K".

Kinds (a `RetrievalSplit` says which applies to it: `RetrievalSplit.relevance`):
- ``one_to_one``: query i matches reference i (CVUSA, CVACT);
- ``positives``: query i matches reference p_i (VIGOR). Its semi-positives are *not* relevant: in the rank they
  count as any other reference; only VIGOR's hit rate sets them aside (`Relevance.hit`);
- ``labels``: every reference with the query's label (University-1652: all images of the building; satellite ->
  drone has about 54 relevant drone images per query). References labelled ``JUNK_LABEL`` count neither way;
- ``radius``: every reference within ``radius_m`` metres of the query (the VPR convention, 25 m by default, as
  gmberton's VPR-methods-evaluation draws it), and with positives given the query's positive too, whatever its
  distance. By the radius alone a query may have no relevant reference.

A relevance holds index tables, not scores: ``relevant`` (Q x G, -1 padding; a row of -1 alone is a query with
nothing relevant, which the scorer counts as a miss at every K),
``semi_positives`` (Q x S, -1 padding, or None), ``ignored_references`` ((N,) bool, or None) and ``ignored``
(Q x S per query, or None: `hit` sets the semi-positives there). The scorer
(`geoloc.eval.scoring`) turns them into ranks with one rule: rank_i = #{j not relevant, not ignored :
s_ij > max_{g relevant} s_ig}.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from torch.nn.utils.rnn import pad_sequence

from geoloc.data.geo import distance_m

__all__ = ["JUNK_LABEL", "RADIUS_M", "Relevance", "index_tensor", "label_tensor"]

JUNK_LABEL = -1
RADIUS_M = 25.0  # the VPR convention (Pitts30k, MSLS): a reference within 25 m of the query is a true match
_DISTANCE_BUDGET = 1 << 22  # query x reference distances per block of the radius search


def index_tensor(x, name: str, shape: tuple[int, ...], n_ref: int, allow_none: bool) -> torch.Tensor:
    """An int64 CPU tensor of ``shape`` indexing ``n_ref`` references (-1 = none where ``allow_none``)."""
    t = torch.as_tensor(x)
    if t.is_floating_point() or t.dtype == torch.bool or t.is_complex():
        raise TypeError(f"{name} must hold integer reference indices, got dtype {t.dtype}")
    if tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    t = t.long().cpu()
    low = -1 if allow_none else 0
    bad = (t < low) | (t >= n_ref)
    if bad.any():
        row = int(torch.nonzero(bad)[0][0])
        raise ValueError(f"{name} of query {row} is {t[row].tolist()}: indices must lie in [{low}, {n_ref})")
    return t


def label_tensor(x, name: str, rows: int) -> torch.Tensor:
    """``x`` as a (rows,) int64 CPU tensor of labels, or an error naming ``name``."""
    t = torch.as_tensor(x)
    if t.is_floating_point() or t.dtype == torch.bool or t.is_complex():
        raise TypeError(f"{name} must hold integer labels, got dtype {t.dtype}")
    if tuple(t.shape) != (rows,):
        raise ValueError(f"{name} must have shape ({rows},), one label per row of its descriptors, "
                         f"got {tuple(t.shape)}")
    return t.long().cpu()


@dataclass(frozen=True, eq=False)
class Relevance:
    """Relevant (and ignored) references of Q queries among N references; build it with a classmethod."""

    kind: str  # one_to_one | positives | labels | radius
    relevant: torch.Tensor  # (Q, G) int64, -1 padding
    num_references: int
    semi_positives: torch.Tensor | None = None  # (Q, S) int64, -1 padding: set aside by the hit rate only
    ignored_references: torch.Tensor | None = None  # (N,) bool: junk, counted neither way for every query
    ignored: torch.Tensor | None = None  # (Q, S) int64, -1 padding: counted neither way for that query

    @property
    def num_queries(self) -> int:
        return int(self.relevant.shape[0])

    @property
    def has_relevant(self) -> torch.Tensor:
        """(Q,) bool: the queries with at least one relevant reference."""
        return (self.relevant >= 0).any(dim=1)

    @classmethod
    def one_to_one(cls, num_queries: int, num_references: int) -> "Relevance":
        """Query i matches reference i; references past Q are distractors."""
        if num_references < num_queries:
            raise ValueError(f"reference[i] must match query[i]: got {num_queries} queries and only "
                             f"{num_references} references (pass positives= when queries share references)")
        return cls("one_to_one", torch.arange(num_queries)[:, None], int(num_references))

    @classmethod
    def from_positives(cls, positives, num_references: int, semi_positives=None,
                       num_queries: int | None = None) -> "Relevance":
        """Query i matches reference positives[i] ((Q,) ints); semi_positives (Q, S), -1 for none (VIGOR)."""
        n_query = len(torch.as_tensor(positives).reshape(-1)) if num_queries is None else num_queries
        pos = index_tensor(positives, "positives", (n_query,), num_references, allow_none=False)
        semi = None
        if semi_positives is not None:
            semi_t = torch.as_tensor(semi_positives)
            if semi_t.ndim != 2 or semi_t.shape[0] != n_query:
                raise ValueError(f"semi_positives must be (Q, S) = ({n_query}, S), got {tuple(semi_t.shape)}")
            semi = index_tensor(semi_t, "semi_positives", tuple(semi_t.shape), num_references, allow_none=True)
        return cls("positives", pos[:, None], int(num_references), semi_positives=semi)

    @classmethod
    def from_labels(cls, query_labels, reference_labels) -> "Relevance":
        """Every reference with the query's label; references labelled JUNK_LABEL are left out of the ranking."""
        r_labels = label_tensor(reference_labels, "reference_labels", len(torch.as_tensor(reference_labels)))
        q_labels = label_tensor(query_labels, "query_labels", len(torch.as_tensor(query_labels)))
        junk = r_labels == JUNK_LABEL
        kept = r_labels[~junk]
        missing = ~torch.isin(q_labels, kept)
        if missing.any():
            i = int(torch.nonzero(missing)[0])
            raise ValueError(
                f"query {i} has label {int(q_labels[i])}, which no reference has (junk references, label "
                f"{JUNK_LABEL}, do not count): average precision is undefined for it ({int(missing.sum())} such "
                "queries). Leave those queries out, or add their places to the gallery.")
        # References grouped by label, in index order within a label; each query takes its label's group.
        order = torch.argsort(r_labels, stable=True)
        labels, counts = torch.unique_consecutive(r_labels[order], return_counts=True)
        starts = torch.cumsum(counts, 0) - counts
        group = torch.searchsorted(labels, q_labels)
        width = int(counts[group].max())
        offsets = torch.arange(width)
        valid = offsets[None, :] < counts[group][:, None]
        at = (starts[group][:, None] + offsets[None, :]).clamp(max=len(order) - 1)
        relevant = torch.where(valid, order[at], torch.full_like(at, -1))
        return cls("labels", relevant, len(r_labels), ignored_references=junk if junk.any() else None)

    @classmethod
    def within_radius(cls, positives, query_positions, reference_positions, kind: str,
                      radius_m: float = RADIUS_M) -> "Relevance":
        """Every reference within ``radius_m`` metres of query i (inclusive), and query i's positive when
        ``positives`` ((Q,) ints) is given; with None the radius alone decides, and a row may be empty.

        positions: (Q, 2) and (N, 2) of one kind, "latlon" (degrees) or "xy" (metres); `geoloc.data.geo.distance_m`.
        """
        if not np.isfinite(radius_m) or radius_m < 0:
            raise ValueError(f"the relevance radius must be a finite number of metres >= 0, got {radius_m}")
        query_positions = np.asarray(query_positions, np.float64)
        reference_positions = np.asarray(reference_positions, np.float64)
        n_query, n_ref = len(query_positions), len(reference_positions)
        pos = None if positives is None else index_tensor(positives, "positives", (n_query,), n_ref, allow_none=False)
        rows = [torch.full((1,), -1)]  # the table is at least one column wide, even when no query has a match
        step = max(1, _DISTANCE_BUDGET // max(1, n_ref))
        for q0 in range(0, n_query, step):
            near = distance_m(query_positions[q0:q0 + step, None, :], reference_positions[None, :, :], kind) <= radius_m
            if pos is not None:
                near[np.arange(len(near)), pos[q0:q0 + step].numpy()] = True  # the positive, whatever its distance
            rows.extend(torch.from_numpy(np.flatnonzero(row)) for row in near)
        return cls("radius", pad_sequence(rows, batch_first=True, padding_value=-1)[1:], n_ref)

    def hit(self) -> "Relevance":
        """VIGOR's hit rate as a rank: the positive is the target and its semi-positives count neither way, so
        hit_i <=> rank 0 <=> no reference outside {p_i} and the semi-positives scores strictly above p_i."""
        if self.semi_positives is None:
            raise ValueError("the hit rate needs semi-positives (VIGOR)")
        return replace(self, semi_positives=None, ignored=self.semi_positives)
