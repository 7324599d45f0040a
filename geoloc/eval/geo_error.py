"""Metre error of the top-1 reference: how far each query's position is from the centre of the tile it retrieved.

VIGOR (Zhu et al., CVPR 2021) gives every panorama and satellite tile a (lat, lon) in its file name; the distance
from a query to its top-1 tile's centre says how far off a retrieval-only localisation is. Distances are
`geoloc.data.geo.distance_m`: haversine for (lat, lon) degrees (sphere of the mean Earth radius), Euclidean for
(x, y) metres. The top-1 is the scorer's (`geoloc.eval.scoring`): the lowest reference index among equal scores.
The summary reports the median and the share of queries within 10 / 25 / 50 m, thresholds inclusive (an error of
exactly 10 m is within 10 m).
"""
from __future__ import annotations

import numpy as np
import torch

from geoloc.data.geo import distance_m
from geoloc.data.relevance import index_tensor
from geoloc.eval.keys import KeySet

__all__ = ["METRE_KEYS", "THRESHOLDS_M", "latlon_array", "metre_errors", "metre_summary"]

THRESHOLDS_M = (10, 25, 50)
METRE_KEYS = KeySet({"median_m": float("inf"), **{f"within_{t}m": 0.0 for t in THRESHOLDS_M}})


def latlon_array(x, name: str, rows: int | None) -> np.ndarray:
    """``x`` as a (rows, 2) float64 array of (lat, lon) degrees (any row count when rows is None), or an error
    naming ``name``."""
    a = np.asarray(x.cpu() if isinstance(x, torch.Tensor) else x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2 or (rows is not None and a.shape[0] != rows):
        want = f"({rows}, 2)" if rows is not None else "(N, 2)"
        raise ValueError(f"{name} must be {want} of (lat, lon) degrees, got shape {a.shape}")
    bad = ~np.isfinite(a).all(axis=1) | (np.abs(a[:, 0]) > 90) | (np.abs(a[:, 1]) > 180)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name} row {i} = {a[i].tolist()} is not a (lat, lon) in degrees")
    return a


def metre_errors(top1, query_positions, reference_positions, kind: str = "latlon") -> np.ndarray:
    """(Q,) float64 metres from query i's position to the centre of its top-1 reference ``top1[i]``.

    top1: (Q,) integer indices into the N references (the scorer's top-1: `geoloc.eval.scoring.top_k`);
    positions (Q, 2) and (N, 2) of one kind: "latlon" degrees (haversine) or "xy" metres (Euclidean).
    """
    if kind == "latlon":
        ref = latlon_array(reference_positions, "reference_latlon", None)
    else:
        ref = np.asarray(reference_positions, np.float64)
    top1 = torch.as_tensor(top1)
    if top1.ndim != 1:
        raise ValueError(f"top1 must be (Q,) reference indices, got shape {tuple(top1.shape)}")
    idx = index_tensor(top1, "top1", tuple(top1.shape), ref.shape[0], allow_none=False).numpy()
    query = (latlon_array(query_positions, "query_latlon", len(idx)) if kind == "latlon"
             else np.asarray(query_positions, np.float64))
    if query.shape != (len(idx), 2) or ref.ndim != 2 or ref.shape[1] != 2:
        raise ValueError(f"positions must be ({len(idx)}, 2) and (N, 2) of {kind}, got {query.shape} and {ref.shape}")
    return distance_m(query, ref[idx], kind)


def metre_summary(errors) -> dict[str, float]:
    """{"median_m", "within_10m", "within_25m", "within_50m"} of (Q,) metre errors, as Python floats.

    The median is numpy's (the mean of the two middle values for an even Q); a share counts errors <= the
    threshold and lies in [0, 1].
    """
    e = checked_errors(errors, "errors")
    return METRE_KEYS.values({"median_m": np.median(e), **shares_within(e, THRESHOLDS_M)})


def checked_errors(errors, what: str) -> np.ndarray:
    """(Q,) errors as float64, refused unless non-empty, 1-D, finite and >= 0 (metres or degrees)."""
    e = np.asarray(errors, dtype=np.float64)
    if e.ndim != 1 or e.size == 0:
        raise ValueError(f"{what} must be a non-empty 1-D array of errors, got shape {e.shape}")
    if not np.isfinite(e).all() or (e < 0).any():
        i = int(np.flatnonzero(~np.isfinite(e) | (e < 0))[0])
        raise ValueError(f"{what} must be finite and >= 0; entry {i} is {e[i]}")
    return e


def shares_within(errors: np.ndarray, thresholds_m, prefix: str = "") -> dict[str, float]:
    """{"<prefix>within_<t>m": share of errors <= t} for each threshold t: inclusive, in [0, 1]."""
    return {f"{prefix}within_{t}m": (errors <= t).mean() for t in thresholds_m}
