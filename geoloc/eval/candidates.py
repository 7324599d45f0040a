"""The scorer's rules on candidate lists: the top-k an index returns instead of every score.

An approximate FAISS index (and the FAISS flat backend of `recall_at_k`) answers each query with k (score, row)
pairs; localize gets one such list per candidate heading. These lists are ranked with the rule of
`geoloc.eval.scoring`, from the returned scores:

- rank_i = #{returned j not relevant, not ignored : s_ij > t_i}, t_i = the best returned relevant score;
- a query none of whose relevant references was returned counts every returned reference against it (rank >= k,
  and no hit), unless ``target_scores`` gives its exact target (what the FAISS flat backend of `recall_at_k`
  does, so that ties at the k-th score count as in the full ranking);
- a query with no relevant reference at all is NO_RELEVANT, past every K, and no hit, as in the full ranking;
- lists are ordered best first, the lower row first among equal scores (`ordered`);
- per-heading lists merge into one by each row's best score over the headings (`merge_headings`), which is the
  max over K of `scoring`: a row of the overall top-k is in the top-k of its best heading.
Rows of -1 (FAISS's "no result") are never relevant and never counted.
"""
from __future__ import annotations

import torch

from geoloc.data.relevance import Relevance
from geoloc.eval.scoring import NO_RELEVANT, Ranking

__all__ = ["merge_headings", "ordered", "rank_candidates"]


def ordered(scores: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(Q x k) lists sorted best first, the lower row first among equal scores, -1 rows last."""
    by_row = torch.sort(torch.where(rows < 0, torch.iinfo(torch.long).max, rows), dim=1, stable=True).indices
    scores, rows = scores.gather(1, by_row), rows.gather(1, by_row)
    by_score = torch.sort(scores, dim=1, descending=True, stable=True).indices
    return scores.gather(1, by_score), rows.gather(1, by_score)


def _member(rows: torch.Tensor, table: torch.Tensor | None) -> torch.Tensor:
    """(Q, k) bool: rows[i, m] is one of table[i]'s indices (-1 padding never matches a row)."""
    if table is None:
        return torch.zeros(rows.shape, dtype=torch.bool)
    return (rows[:, :, None] == table[:, None, :]).any(dim=2) & (rows >= 0)


def _counts(scores, rows, relevant, excluded, target_scores) -> torch.Tensor:
    found = relevant.any(dim=1)
    target = scores.masked_fill(~relevant, float("-inf")).max(dim=1).values
    if target_scores is not None:
        target = torch.where(found, target, target_scores.to(scores.dtype))
    counted = ~excluded & (rows >= 0)
    count = ((scores > target[:, None]) & counted).sum(dim=1)
    if target_scores is None:
        count = torch.where(found, count, counted.sum(dim=1))
    return count


def rank_candidates(scores: torch.Tensor, rows: torch.Tensor, relevance: Relevance, hits: bool = False,
                    target_scores: torch.Tensor | None = None) -> Ranking:
    """A `Ranking` (ranks, hits, the lists as the top-k) of Q x k candidate lists, by the module's rule.

    target_scores: (Q,) the exact t_i (`scoring.relevant_scores`) for queries whose relevant references were not
    returned, or None.
    """
    scores, rows = ordered(scores.cpu(), rows.cpu().long())
    relevant = _member(rows, relevance.relevant)
    junk = (torch.zeros(rows.shape, dtype=torch.bool) if relevance.ignored_references is None else
            relevance.ignored_references[rows.clamp(min=0)] & (rows >= 0))
    ignored = junk | _member(rows, relevance.ignored)
    found = relevance.has_relevant
    out = Ranking(_counts(scores, rows, relevant, relevant | ignored, target_scores).masked_fill(~found, NO_RELEVANT),
                  torch.zeros(rows.shape[0], dtype=torch.long), top_scores=scores, top_rows=rows)
    if hits:
        hit = relevance.hit()
        counts = _counts(scores, rows, relevant, relevant | junk | _member(rows, hit.ignored), target_scores)
        out.hits = (counts == 0) & found
    return out


def merge_headings(scores: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Q x K x k per-heading lists -> (Q x M scores, Q x M rows, Q x M heading k) with each row once, at its best
    score over the K lists (the first heading among equal scores), ordered as `ordered`. M = the most distinct rows
    of any query; shorter lists end in (-inf, -1, -1)."""
    n_query, n_heading, k = rows.shape
    heading = torch.arange(n_heading).repeat_interleave(k).expand(n_query, -1)
    flat_scores, flat_rows = scores.reshape(n_query, -1), rows.reshape(n_query, -1).long()
    # By row, and within a row best score first, then the first heading: the first entry of each row is its best.
    by_score = torch.sort(flat_scores, dim=1, descending=True, stable=True).indices
    key = torch.where(flat_rows < 0, torch.iinfo(torch.long).max, flat_rows).gather(1, by_score)
    by_row = torch.sort(key, dim=1, stable=True).indices
    pick = by_score.gather(1, by_row)
    s, r, h = flat_scores.gather(1, pick), flat_rows.gather(1, pick), heading.gather(1, pick)
    first = torch.ones_like(r, dtype=torch.bool)
    first[:, 1:] = r[:, 1:] != r[:, :-1]
    keep = first & (r >= 0)
    s = s.masked_fill(~keep, float("-inf"))
    r, h = r.masked_fill(~keep, -1), h.masked_fill(~keep, -1)
    width = max(1, int(keep.sum(dim=1).max()))
    order = torch.sort(torch.where(keep, r, torch.iinfo(torch.long).max), dim=1, stable=True).indices
    s, r, h = s.gather(1, order), r.gather(1, order), h.gather(1, order)
    by_score = torch.sort(s, dim=1, descending=True, stable=True).indices[:, :width]
    return s.gather(1, by_score), r.gather(1, by_score), h.gather(1, by_score)
