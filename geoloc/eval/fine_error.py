"""Fine-grained (metric) localisation errors: how far a refined position is from the truth, in metres, and how far
a refined heading is, in degrees.

- with the positive tile given (the fine-grained protocol of CCVPE and SliceMatch): `fine_mean_m`,
  `fine_median_m`, `fine_within_{1,3,5}m`; with an unknown heading `fine_heading_mean_deg`,
  `fine_heading_median_deg`;
- over the whole tile, each query refined in every tile that holds it (its positive and the semi-positives whose
  truth lies inside them, so the truths cover the tile): `whole_tile_mean_m`, `whole_tile_median_m`,
  `whole_tile_within_{1,3,5}m`, and the median of the truths near the edge (`whole_tile_edge_median_m`: within 0.1
  of an edge, a tile fraction below 0.1 or above 0.9 on either axis) and in the tile's central half
  (`whole_tile_centre_median_m`: fractions 0.25-0.75 on both axes), NaN where no truth lies there;
- end to end, the top-1 retrieved tile refined: `e2e_median_m`, `e2e_within_{25,50,100}m`.
Shares count errors <= the threshold (inclusive), as geo_error.py's do.
"""
from __future__ import annotations

import numpy as np

from geoloc.eval.geo_error import checked_errors, shares_within
from geoloc.eval.keys import KeySet

FINE_THRESHOLDS_M = (1, 3, 5)
E2E_THRESHOLDS_M = (25, 50, 100)
FINE_KEYS = KeySet({"fine_mean_m": float("inf"), "fine_median_m": float("inf"),
                    **{f"fine_within_{t}m": 0.0 for t in FINE_THRESHOLDS_M}})
FINE_HEADING_KEYS = KeySet({"fine_heading_mean_deg": 180.0, "fine_heading_median_deg": 180.0})
WHOLE_TILE_KEYS = KeySet({"whole_tile_mean_m": float("inf"), "whole_tile_median_m": float("inf"),
                          **{f"whole_tile_within_{t}m": 0.0 for t in FINE_THRESHOLDS_M},
                          "whole_tile_edge_median_m": float("inf"), "whole_tile_centre_median_m": float("inf")})
EDGE_FRACTION = 0.1  # a truth this close to an edge, as a share of the tile's side, is an edge truth
E2E_KEYS = KeySet({"e2e_median_m": float("inf"), **{f"e2e_within_{t}m": 0.0 for t in E2E_THRESHOLDS_M}})


def near_edge(fractions):
    """(N,) whether each of (N, 2) tile fractions (numpy or torch) lies within EDGE_FRACTION of an edge: an edge truth."""
    return ((fractions < EDGE_FRACTION) | (fractions > 1 - EDGE_FRACTION)).any(1)


def fine_summary(errors_m) -> dict[str, float]:
    """FINE_KEYS of (Q,) metre errors with the positive tile given; with no error (no query's position in its
    tile is known), every key at its worst."""
    if np.asarray(errors_m).shape == (0,):
        return dict(FINE_KEYS.worst)
    e = checked_errors(errors_m, "fine errors")
    return FINE_KEYS.values({"fine_mean_m": e.mean(), "fine_median_m": np.median(e),
                             **shares_within(e, FINE_THRESHOLDS_M, "fine_")})


def whole_tile_summary(errors_m, truth_fraction) -> dict[str, float]:
    """WHOLE_TILE_KEYS of (P,) metre errors of query-tile pairs whose truths lie at the (P, 2) tile fractions; with
    no pair, every key at its worst."""
    if np.asarray(errors_m).shape == (0,):
        return dict(WHOLE_TILE_KEYS.worst)
    e = checked_errors(errors_m, "whole-tile errors")
    f = np.asarray(truth_fraction, np.float64)
    edge = near_edge(f)
    centre = ((f >= 0.25) & (f <= 0.75)).all(1)
    median = lambda part: float(np.median(e[part])) if part.any() else float("nan")  # noqa: E731
    return WHOLE_TILE_KEYS.values({"whole_tile_mean_m": e.mean(), "whole_tile_median_m": np.median(e),
                                   **shares_within(e, FINE_THRESHOLDS_M, "whole_tile_"),
                                   "whole_tile_edge_median_m": median(edge),
                                   "whole_tile_centre_median_m": median(centre)})


def heading_summary(errors_deg) -> dict[str, float]:
    """FINE_HEADING_KEYS of (Q,) circular heading errors in [0, 180] degrees."""
    e = checked_errors(errors_deg, "heading errors")
    return FINE_HEADING_KEYS.values({"fine_heading_mean_deg": e.mean(), "fine_heading_median_deg": np.median(e)})


def e2e_summary(errors_m) -> dict[str, float]:
    """E2E_KEYS of (Q,) metre errors of the refined top-1 tile."""
    e = checked_errors(errors_m, "end-to-end errors")
    return E2E_KEYS.values({"e2e_median_m": np.median(e),
                            **shares_within(e, E2E_THRESHOLDS_M, "e2e_")})
