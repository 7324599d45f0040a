"""Queries of unknown heading: their candidate inputs, and retrieval and heading estimation scored by a search over
candidate headings.

Each query i is encoded at K candidate headings h_k = 360·k/K (its view placed on the 360° canvas at h_k, then
aligned: `query_inputs`, geometry in views.py), giving q_ik. With references r_j (N×D), the scorer
(`geoloc.eval.scoring`, queries Q×K×D) gives:
- score(i, j) = max_k <q_ik, r_j>: a circular correlation over azimuth, computed through the query encoder, that
  keeps retrieval a single-vector search (DSM, Shi et al. CVPR 2020, correlates feature maps instead);
- rank(i) = #{j != p_i : score(i, j) > score(i, p_i)} (ties in the query's favour: the one rank rule);
- the heading estimate for the true pair is h_k* with k* = argmax_k <q_ik, r_{p_i}> (the first k on ties), and
  its error is the circular distance to the true heading, in [0, 180] degrees. A query with no relevant
  reference (own data under the radius rule) has no true pair: it counts in the recall, not in the heading.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch

from geoloc.config import ConfigError
from geoloc.data.relevance import Relevance
from geoloc.eval.keys import KeySet
from geoloc.eval.recall import check_ks, recall_keys, recall_summary
from geoloc.eval.scoring import rank
from geoloc.tasks.crossview.transforms import align_query, image_tensor, normalise
from geoloc.tasks.crossview.views import candidate_headings, check_fov, circular_error_deg, view_canvases

HEADING_WITHIN_DEG = (10, 20)  # shares of queries within these errors (DSM reports such orientation accuracies)
HEADING_KEYS = KeySet({"heading_median_deg": 180.0, "heading_mean_deg": 180.0,
                       **{f"heading_within_{limit}deg": 0.0 for limit in HEADING_WITHIN_DEG}})


def query_candidates(street: np.ndarray, cfg, view: str, fov_deg: float,
                     steps: int) -> tuple[torch.Tensor, np.ndarray]:
    """One street view of unknown heading → (K×3×H×W uint8 query-branch images, as a data worker returns them,
    (K,) candidate headings in degrees).

    Candidate k is the view at heading 360·k/K (`query_images`)."""
    headings = candidate_headings(steps)
    return query_images(street, cfg, view, fov_deg, headings), headings


def query_images(street: np.ndarray, cfg, view: str, fov_deg: float, headings) -> torch.Tensor:
    """len(headings)×3×H×W uint8 query-branch images: the view placed on the 360° canvas at each heading (degrees),
    aligned as the dataset config `cfg` (a CrossViewDataConfig) says. `view` is the split's query view
    ("panorama", or "sphere" already cut to its horizon band by load_view)."""
    if view not in ("panorama", "sphere"):
        raise ConfigError(f"a heading search needs panorama-like queries (view 'panorama' or 'sphere'), got view "
                          f"{view!r}: photos (e.g. drone views) have no bearing geometry")
    fov = check_fov(fov_deg)
    return torch.stack([image_tensor(align_query(canvas, cfg, view, wrapped=True))
                        for canvas in view_canvases(street, fov, headings)])


def query_inputs(street: np.ndarray, cfg, view: str, fov_deg: float, headings) -> torch.Tensor:
    """`query_images` normalised (transforms.normalise): the float query-branch inputs the apps encode."""
    return normalise(query_images(street, cfg, view, fov_deg, headings))


def candidate_descriptors(encoder, candidates: torch.Tensor) -> torch.Tensor:
    """B×K×3×H×W candidate inputs (K headings per query) -> B×K×D descriptors, encoded B images at a time as
    without the search: K·B at once would hold K times the activations."""
    flat = candidates.flatten(0, 1)
    return torch.cat([encoder(part) for part in flat.split(candidates.shape[0])]).unflatten(0, candidates.shape[:2])


def heading_plan(ks: Iterable[int] = (1, 5, 10)) -> list:
    """The key sets `heading_metrics` reports (its collapsed result is `geoloc.eval.keys.collapsed` of them)."""
    return [recall_keys(check_ks(ks)), HEADING_KEYS]


def heading_metrics(query: torch.Tensor, reference: torch.Tensor, true_heading, ks: Iterable[int] = (1, 5, 10),
                    relevance: Relevance | None = None) -> dict[str, float]:
    """R@K, R@1% (K = max(1, floor(N/100))) of the max-over-headings score and the heading error of the true pair:
    heading_median_deg, heading_mean_deg and heading_within_{10,20}deg (shares in [0, 1]).

    query: Q×K×D (candidate k placed at heading 360·k/K); reference: N×D; true_heading: (Q,) degrees; relevance:
    default one-to-one (query i's reference is i)."""
    ks = check_ks(ks)
    if query.ndim != 3:
        raise ValueError(f"query must be Q x K x D (K candidate headings per query), got shape {tuple(query.shape)}")
    relevance = relevance or Relevance.one_to_one(query.shape[0], reference.shape[0])
    found = rank(query, reference, relevance)
    truth = np.asarray(torch.as_tensor(true_heading).double().cpu())
    if truth.shape != (query.shape[0],):
        raise ValueError(f"true_heading must be ({query.shape[0]},) degrees, got shape {truth.shape}")
    candidate = found.best_candidate.numpy()
    paired = candidate >= 0  # a query with nothing relevant has no true pair to read a heading from
    out = recall_summary(found.ranks, ks, reference.shape[0])
    if not paired.any():
        return {**out, **HEADING_KEYS.worst}
    error = circular_error_deg(candidate_headings(query.shape[1])[candidate[paired]], truth[paired])
    out.update(HEADING_KEYS.values({
        "heading_median_deg": np.median(error), "heading_mean_deg": error.mean(),
        **{f"heading_within_{limit}deg": (error <= limit).mean() for limit in HEADING_WITHIN_DEG}}))
    return out
