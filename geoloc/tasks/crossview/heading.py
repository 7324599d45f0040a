"""Queries of unknown heading: their candidate inputs, and retrieval and heading estimation scored by a search over
candidate headings.

Each query i is encoded at K candidate headings h_k = 360·k/K (its view placed on the 360° canvas at h_k, then
aligned: `query_inputs`, geometry in views.py), giving q_ik. With references r_j (N×D):
- score(i, j) = max_k <q_ik, r_j>: a circular correlation over azimuth, computed through the query encoder, that
  keeps retrieval a single-vector search (DSM, Shi et al. CVPR 2020, correlates feature maps instead);
- rank(i) = #{j != p_i : score(i, j) > score(i, p_i)} (ties in the query's favour, as geoloc.eval.recall);
- the heading estimate for the true pair is h_k* with k* = argmax_k <q_ik, r_{p_i}>, and its error is the
  circular distance to the true heading, in [0, 180] degrees.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch

from geoloc.config import ConfigError
from geoloc.eval.descriptors import unit_rows
from geoloc.eval.recall import one_percent_k
from geoloc.tasks.crossview.transforms import align_query, to_tensor
from geoloc.tasks.crossview.views import candidate_headings, check_fov, circular_error_deg, view_canvas

HEADING_WITHIN_DEG = (10, 20)  # shares of queries within these errors (DSM reports such orientation accuracies)
SCORES_PER_CHUNK = 2 ** 25


def query_candidates(street: np.ndarray, cfg, view: str, fov_deg: float,
                     steps: int) -> tuple[torch.Tensor, np.ndarray]:
    """One street view of unknown heading → (K×3×H×W query-branch inputs, (K,) candidate headings in degrees).

    Candidate k is the view at heading 360·k/K (`query_inputs`)."""
    headings = candidate_headings(steps)
    return query_inputs(street, cfg, view, fov_deg, headings), headings


def query_inputs(street: np.ndarray, cfg, view: str, fov_deg: float, headings) -> torch.Tensor:
    """len(headings)×3×H×W query-branch inputs: the view placed on the 360° canvas at each heading (degrees),
    aligned as the dataset config `cfg` (a CrossViewDataConfig) says and normalised like `to_tensor`. `view` is
    the split's query view ("panorama", or "sphere" already cut to its horizon band by load_view)."""
    if view not in ("panorama", "sphere"):
        raise ConfigError(f"a heading search needs panorama-like queries (view 'panorama' or 'sphere'), got view "
                          f"{view!r}: photos (e.g. drone views) have no bearing geometry")
    fov = check_fov(fov_deg)
    return torch.stack([to_tensor(align_query(view_canvas(street, fov, h), cfg, view)) for h in headings])


def heading_search(query: torch.Tensor, reference: torch.Tensor,
                   positives: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """query: Q×K×D candidate descriptors; reference: N×D; positives: (Q,) p_i (default i).

    Returns (rank (Q,) long, best candidate k* (Q,) long) as defined in the module docstring, on the CPU. Rows
    are L2-normalised when off unit length; non-finite or zero rows raise. Chunked over queries so that about
    2^25 scores are in memory at once, never the whole Q×K×N tensor.
    """
    if query.ndim != 3:
        raise ValueError(f"query must be Q x K x D (K candidate headings per query), got shape {tuple(query.shape)}")
    n_query, k, dim = query.shape
    if reference.ndim != 2 or reference.shape[1] != dim:
        raise ValueError(f"reference must be N x {dim}, got shape {tuple(reference.shape)}")
    q = unit_rows(query.reshape(n_query * k, dim).float(), "query").reshape(n_query, k, dim)
    r = unit_rows(reference.float(), "reference").to(q.device)
    pos = torch.arange(n_query) if positives is None else torch.as_tensor(positives).long().cpu()
    if pos.shape != (n_query,) or (pos < 0).any() or (pos >= r.shape[0]).any():
        raise ValueError(f"positives must be ({n_query},) indices into {r.shape[0]} references")
    step = max(1, SCORES_PER_CHUNK // max(1, k * r.shape[0]))
    ranks, best = torch.empty(n_query, dtype=torch.long), torch.empty(n_query, dtype=torch.long)
    for q0 in range(0, n_query, step):
        chunk = q[q0:q0 + step]
        rows = torch.arange(chunk.shape[0])
        p = pos[q0:q0 + chunk.shape[0]].to(q.device)
        scores = torch.einsum("qkd,nd->qkn", chunk, r)  # q×K×N
        own_per_k = scores[rows, :, p]  # q×K: each candidate against the true reference
        best[q0:q0 + chunk.shape[0]] = own_per_k.argmax(dim=1).cpu()
        top = scores.max(dim=1).values  # q×N
        own = top[rows, p]
        beats = top > own[:, None]
        beats[rows, p] = False  # the positive never counts against itself
        ranks[q0:q0 + chunk.shape[0]] = beats.sum(dim=1).cpu()
    return ranks, best


def heading_metrics(query: torch.Tensor, reference: torch.Tensor, true_heading, ks: Iterable[int] = (1, 5, 10),
                    positives: torch.Tensor | None = None) -> dict[str, float]:
    """R@K, R@1% (K = max(1, floor(N/100))) of the max-over-headings score and the heading error of the true pair:
    heading_median_deg, heading_mean_deg and heading_within_{10,20}deg (shares in [0, 1]).

    query: Q×K×D (candidate k placed at heading 360·k/K); reference: N×D; true_heading: (Q,) degrees."""
    ranks, best = heading_search(query, reference, positives)
    truth = np.asarray(torch.as_tensor(true_heading).double().cpu())
    if truth.shape != (query.shape[0],):
        raise ValueError(f"true_heading must be ({query.shape[0]},) degrees, got shape {truth.shape}")
    error = circular_error_deg(candidate_headings(query.shape[1])[best.numpy()], truth)
    out = {f"R@{k}": float((ranks < k).double().mean()) for k in ks}
    out["R@1%"] = float((ranks < one_percent_k(reference.shape[0])).double().mean())
    out["heading_median_deg"] = float(np.median(error))
    out["heading_mean_deg"] = float(error.mean())
    for limit in HEADING_WITHIN_DEG:
        out[f"heading_within_{limit}deg"] = float((error <= limit).mean())
    return out


def collapsed_heading_metrics(ks: Iterable[int] = (1, 5, 10)) -> dict[str, float]:
    """The worst value of every heading_metrics key, reported when the references have collapsed."""
    out = {**{f"R@{k}": 0.0 for k in ks}, "R@1%": 0.0, "heading_median_deg": 180.0, "heading_mean_deg": 180.0}
    return {**out, **{f"heading_within_{limit}deg": 0.0 for limit in HEADING_WITHIN_DEG}}
