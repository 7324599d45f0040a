"""The scorer: one chunked query x reference score stream, one rank rule, one top-k tie rule.

Every number geoloc reports about a ranking comes from here: recall and R@1% (`recall.py`), VIGOR's hit rate,
University-1652's AP (`average_precision.py`), the top-1 of the metre error, the heading search (each query as K
candidate descriptors), the saved-gallery path, the figures, localize and MMDIP's fused ranking.

Scores are inner products of unit rows (d = 2 - 2 a.b, docs/conventions.md "Descriptors"). A query may be Q x D,
or Q x K x D: K candidate descriptors (headings) whose score against a reference is the best of the K,
s_ij = max_k <q_ik, r_j>.

**The rank rule.** With query i's relevant references R_i and ignored references I_i (`geoloc.data.relevance`),

    rank_i = #{j not in R_i or I_i : s_ij > t_i},   t_i = max_{g in R_i} s_ig,

so a tie counts in the query's favour. A query with no relevant reference (R_i empty: the radius rule alone) has
nothing to find: its rank is NO_RELEVANT, past every K, so it is a miss at every K and still counts in every
mean (gmberton's VPR-methods-evaluation counts such a query the same way), and it has no hit, no relevant
position and no best candidate (-1). The same count against other targets gives the rest:
- VIGOR's hit (`Relevance.hit`): target s_{i,p_i}, the semi-positives ignored; hit_i <=> count = 0;
- AP: each relevant g's count of the non-relevant references above s_ig gives its position in the ranking.
Each target is the row-wise product sum(q_i * r_g) (max over K first), compared with the block products
q_chunk @ r_block.T; a relevant reference never counts against itself, whatever rounding the two products got.
Ties are ties of this arithmetic: a non-relevant duplicate of a relevant reference may score a last bit above
the target; products that are exact in any order (the tests' ties) tie on every path and every blocking.

**Top-k** lists are best first, the lower reference index first among equal scores, whatever the blocking.

**Memory.** Queries go ``chunk_size`` (default 1024) at a time against blocks of SCORE_BUDGET / (chunk_size * K)
references: about 2^25 scores (128 MiB of float32) at once, never Q x N. Everything runs on the device the
references live on; results come back on the CPU.

Candidate lists (what an approximate index returns, or the per-heading lists localize merges) follow the same
rule in `candidates.py`.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from geoloc.data.relevance import Relevance
from geoloc.eval.descriptors import checked_pair

__all__ = ["NO_RELEVANT", "QUERY_CHUNK", "SCORE_BUDGET", "Ranking", "check_chunk", "rank", "relevant_scores",
           "top_k"]

NO_RELEVANT = torch.iinfo(torch.long).max  # the rank of a query with no relevant reference: past every K
QUERY_CHUNK = 1024
SCORE_BUDGET = 1 << 25  # scores in one query chunk x reference block
COMPARE_TARGETS = 4  # up to this many targets per query are counted by comparison, more by one sort per block


def check_chunk(chunk_size: int | None) -> int:
    """Queries per block: ``chunk_size`` or QUERY_CHUNK; a ValueError below 1."""
    chunk = int(chunk_size or QUERY_CHUNK)
    if chunk < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    return chunk


def _reference_block(chunk: int, candidates: int) -> int:
    return max(1, SCORE_BUDGET // max(1, chunk * candidates))


def _block_scores(qc: torch.Tensor, rb: torch.Tensor) -> torch.Tensor:
    """(c, B) scores of a query chunk (c x D, or c x K x D: max over K) against a reference block (B x D)."""
    if qc.ndim == 2:
        return qc @ rb.t()
    c, k, d = qc.shape
    return (qc.reshape(c * k, d) @ rb.t()).view(c, k, -1).amax(dim=1)


def _pair_scores(qc: torch.Tensor, r: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Row-wise scores of each query against its references ``rows`` (c x G, -1 = none: -inf), and for c x K x D
    queries the candidate k of each (first on ties; zeros for c x D)."""
    scores = torch.full(rows.shape, float("-inf"), dtype=qc.dtype, device=qc.device)
    best_k = torch.zeros(rows.shape, dtype=torch.long, device=qc.device)
    for g in range(rows.shape[1]):
        col = rows[:, g]
        if qc.ndim == 2:
            s = (qc * r[col.clamp(min=0)]).sum(dim=1)
        else:
            s, best_k[:, g] = (qc * r[col.clamp(min=0)][:, None, :]).sum(dim=2).max(dim=1)
        scores[:, g] = s.masked_fill(col < 0, float("-inf"))
    return scores, best_k


def _mark(tables: list[torch.Tensor], r0: int, width: int, out: torch.Tensor) -> torch.Tensor:
    """Set out[i, j - r0] for every index j of row i of each (c, G) table that lies in [r0, r0 + width)."""
    rows = torch.arange(out.shape[0], device=out.device)
    for table in tables:
        for g in range(table.shape[1]):
            cols = table[:, g]
            inside = (cols >= r0) & (cols < r0 + width)
            out[rows[inside], cols[inside] - r0] = True
    return out


def _excluded(tables: list[torch.Tensor], ignored_references: torch.Tensor | None, r0: int, width: int,
              c: int, device) -> torch.Tensor:
    out = torch.zeros(c, width, dtype=torch.bool, device=device)
    _mark(tables, r0, width, out)
    if ignored_references is not None:
        out |= ignored_references[r0:r0 + width].to(device)[None, :]
    return out


def _count_above(scores: torch.Tensor, excluded: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """(c, T) counts of the references not excluded with a score strictly above each target (c, T)."""
    if targets.shape[1] <= COMPARE_TARGETS:
        return torch.stack([((scores > targets[:, t:t + 1]) & ~excluded).sum(dim=1)
                            for t in range(targets.shape[1])], dim=1)
    # Many targets per query (AP over a building's images): one sort, then a binary search per target.
    ordered = scores.masked_fill(excluded, float("-inf")).sort(dim=1).values
    at_or_below = torch.searchsorted(ordered, targets.contiguous(), right=True)
    return scores.shape[1] - at_or_below


def _block_top(scores: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(c, k) best scores of a block and their columns, best first, the lower column first among equal scores."""
    k = min(k, scores.shape[1])
    kth = scores.topk(k, dim=1).values[:, -1:]
    take = scores > kth
    tie = scores == kth
    need = k - take.sum(dim=1, keepdim=True)
    surplus = (tie.sum(dim=1, keepdim=True) > need).squeeze(1)
    if surplus.any():  # more ties at the k-th score than places left: the lowest columns get them
        sub = tie[surplus]
        sub &= torch.cumsum(sub, dim=1, dtype=torch.int32) <= need[surplus]
        tie[surplus] = sub
    take |= tie
    cols = torch.nonzero(take)[:, 1].view(scores.shape[0], k)  # row-major: ascending columns within a row
    vals = scores.gather(1, cols)
    order = vals.sort(dim=1, descending=True, stable=True).indices
    return vals.gather(1, order), cols.gather(1, order)


def _merge_top(best: tuple[torch.Tensor, torch.Tensor] | None, block: tuple[torch.Tensor, torch.Tensor],
               k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The best k of two lists, the first holding the lower reference indices (so it wins ties)."""
    if best is None:
        return block
    vals, rows = torch.cat([best[0], block[0]], dim=1), torch.cat([best[1], block[1]], dim=1)
    order = vals.sort(dim=1, descending=True, stable=True).indices[:, :k]
    return vals.gather(1, order), rows.gather(1, order)


@dataclass
class Ranking:
    """What one pass of the stream found, on the CPU (Q queries, N references).

    ranks (Q,): the rank rule against the best relevant reference (NO_RELEVANT for a query without one);
    best_candidate (Q,): for Q x K x D queries, the candidate k scoring that reference highest (0 otherwise; -1
    for a query without a relevant reference);
    hits (Q,) bool or None: VIGOR's hit (`Relevance.hit`), asked with ``hits=True``;
    relevant_ranks (Q, G) or None: 0-based positions of every relevant reference, ascending, -1 padding
    (``every_relevant=True``);
    top_scores, top_rows (Q, k) or None: the top-k (``top=k``).
    """

    ranks: torch.Tensor
    best_candidate: torch.Tensor
    hits: torch.Tensor | None = None
    relevant_ranks: torch.Tensor | None = None
    top_scores: torch.Tensor | None = None
    top_rows: torch.Tensor | None = None


def _positions(counts: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Each relevant reference's 0-based position from its count of counted references above it: sorted by
    count, the m-th relevant one (0-based) sits at m + its count (relevant ones tied with others come first)."""
    big = torch.iinfo(torch.long).max
    ordered = counts.masked_fill(~valid, big).sort(dim=1).values
    position = ordered + torch.arange(counts.shape[1])[None, :]
    return position.masked_fill(ordered == big, -1)


def rank(query, reference, relevance: Relevance | None, hits: bool = False, every_relevant: bool = False,
         top: int = 0, chunk_size: int | None = None) -> Ranking:
    """One pass of the score stream: ranks, and on request hits, every relevant reference's position, the top-k.

    query: Q x D or Q x K x D; reference: N x D (tensors or numpy; `checked_pair`); relevance: for these Q
    queries and N references (None: the top-k only, ``ranks`` then all 0). See the module docstring for the rules
    and the memory budget.
    """
    chunk = check_chunk(chunk_size)
    q, r = checked_pair(query, reference)
    if relevance is not None and (relevance.num_queries, relevance.num_references) != (q.shape[0], r.shape[0]):
        raise ValueError(f"the relevance is for {relevance.num_queries} queries and {relevance.num_references} "
                         f"references, the descriptors are {q.shape[0]} and {r.shape[0]}")
    n_query, device = q.shape[0], r.device
    step = _reference_block(chunk, q.shape[1] if q.ndim == 3 else 1)
    top = min(int(top), r.shape[0])
    out = Ranking(torch.zeros(n_query, dtype=torch.long), torch.zeros(n_query, dtype=torch.long),
                  hits=torch.empty(n_query, dtype=torch.bool) if hits else None)
    every, tops = [], []
    for q0 in range(0, n_query, chunk):
        qc = q[q0:q0 + chunk]
        c = qc.shape[0]
        counts = beaten = best_top = None
        if relevance is not None:
            relevant = relevance.relevant[q0:q0 + c].to(device)
            each, each_k = _pair_scores(qc, r, relevant)
            best, arg = each.max(dim=1, keepdim=True)
            targets = torch.cat([best, each], dim=1) if every_relevant else best
            excluded = [relevant] + _rows(relevance.ignored, q0, c, device)
            counts = torch.zeros(targets.shape, dtype=torch.long, device=device)
            if hits:  # the hit's target is the positive (best) too; its semi-positives are set aside
                hit_rel = relevance.hit()
                hit_excluded = [relevant] + _rows(hit_rel.ignored, q0, c, device)
                beaten = torch.zeros(c, 1, dtype=torch.long, device=device)
        for r0 in range(0, r.shape[0], step):
            scores = _block_scores(qc, r[r0:r0 + step])
            width = scores.shape[1]
            if counts is not None:
                counts += _count_above(scores, _excluded(excluded, relevance.ignored_references, r0, width, c,
                                                         device), targets)
            if beaten is not None:
                beaten += _count_above(scores, _excluded(hit_excluded, hit_rel.ignored_references, r0, width, c,
                                                         device), best)
            if top:
                vals, cols = _block_top(scores, top)
                best_top = _merge_top(best_top, (vals, cols + r0), top)
        if counts is not None:
            found = relevance.has_relevant[q0:q0 + c]
            out.ranks[q0:q0 + c] = counts[:, 0].cpu().masked_fill(~found, NO_RELEVANT)
            out.best_candidate[q0:q0 + c] = each_k.gather(1, arg)[:, 0].cpu().masked_fill(~found, -1)
        if beaten is not None:
            out.hits[q0:q0 + c] = (beaten[:, 0] == 0).cpu() & found
        if every_relevant and counts is not None:
            every.append(_positions(counts[:, 1:].cpu(), (relevant >= 0).cpu()))
        if top:
            tops.append((best_top[0].cpu(), best_top[1].cpu()))
    if every:
        out.relevant_ranks = torch.cat(every)
    if top:
        out.top_scores, out.top_rows = torch.cat([t[0] for t in tops]), torch.cat([t[1] for t in tops])
    return out


def _rows(table: torch.Tensor | None, q0: int, c: int, device) -> list[torch.Tensor]:
    return [] if table is None else [table[q0:q0 + c].to(device)]


def top_k(query, reference, k: int, chunk_size: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(Q x k scores, Q x k reference rows) on the CPU, best first, the lower row first among equal scores; k is
    capped at N. query: Q x D or Q x K x D (max over K); reference: N x D."""
    if int(k) < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    found = rank(query, reference, None, top=k, chunk_size=chunk_size)
    return found.top_scores, found.top_rows


def relevant_scores(query, reference, relevance: Relevance) -> torch.Tensor:
    """(Q,) t_i = max over query i's relevant references of the row-wise score: the target of the rank rule."""
    q, r = checked_pair(query, reference)
    out = []
    for q0 in range(0, q.shape[0], QUERY_CHUNK):
        qc = q[q0:q0 + QUERY_CHUNK]
        out.append(_pair_scores(qc, r, relevance.relevant[q0:q0 + qc.shape[0]].to(r.device))[0].max(dim=1)[0].cpu())
    return torch.cat(out)
