"""Metre error of the top-1 reference: how far each query's GPS is from the centre of the tile it retrieved.

VIGOR (Zhu et al., CVPR 2021) gives every panorama and satellite tile a (lat, lon) in its file name; the distance
from a query to its top-1 tile's centre says how far off a retrieval-only localisation is. Distances are
`geoloc.data.geo.haversine_m` (sphere of the mean Earth radius). The summary reports the median and the share of
queries within 10 / 25 / 50 m, thresholds inclusive (an error of exactly 10 m is within 10 m).
"""
from __future__ import annotations

import numpy as np
import torch

from geoloc.data.geo import haversine_m
from geoloc.eval.gallery import _chunk_rows
from geoloc.eval.recall import _check_chunk, _check_pair, _index_tensor

__all__ = ["THRESHOLDS_M", "latlon_array", "metre_errors", "metre_summary", "top1_indices"]

THRESHOLDS_M = (10, 25, 50)


def top1_indices(query, reference, chunk_size: int | None = None) -> torch.Tensor:
    """(Q,) int64 on the CPU: the index of the reference with the largest inner product with each query.

    query: Q x D, reference: N x D (tensors or numpy arrays), L2-normalised as in `recall_at_k` (rows off unit
    length are normalised; NaN/inf or all-zero rows raise). Ties go to the lowest reference index (a fixed rule
    that does not depend on the chunking). At most ``chunk_size`` queries (default 1024) times a block of
    references are scored at once; runs where ``reference`` lives (GPU if there).
    """
    chunk = _check_chunk(chunk_size)
    q, r = _check_pair(query, reference, one_to_one=False)
    step = _chunk_rows(chunk)
    out = torch.empty(q.shape[0], dtype=torch.long)
    for q0 in range(0, q.shape[0], chunk):
        qc = q[q0:q0 + chunk]
        best = torch.full((qc.shape[0],), float("-inf"), dtype=r.dtype, device=r.device)
        best_idx = torch.zeros(qc.shape[0], dtype=torch.long, device=r.device)
        for r0 in range(0, r.shape[0], step):
            # max() returns the first index of a row's maximum; a later block takes over only when strictly
            # better, so the lowest index wins a tie across blocks too.
            score, idx = (qc @ r[r0:r0 + step].t()).max(dim=1)
            better = score > best
            best = torch.where(better, score, best)
            best_idx = torch.where(better, idx + r0, best_idx)
        out[q0:q0 + qc.shape[0]] = best_idx.cpu()
    return out


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


def metre_errors(top1, query_latlon, reference_latlon) -> np.ndarray:
    """(Q,) float64 metres from query i's (lat, lon) to the centre of its top-1 reference ``top1[i]``.

    top1: (Q,) integer indices into the N references (e.g. `top1_indices`); query_latlon (Q, 2) and
    reference_latlon (N, 2) in degrees.
    """
    ref = latlon_array(reference_latlon, "reference_latlon", None)
    top1 = torch.as_tensor(top1)
    if top1.ndim != 1:
        raise ValueError(f"top1 must be (Q,) reference indices, got shape {tuple(top1.shape)}")
    idx = _index_tensor(top1, "top1", tuple(top1.shape), ref.shape[0], allow_none=False).numpy()
    return haversine_m(latlon_array(query_latlon, "query_latlon", len(idx)), ref[idx])


def metre_summary(errors) -> dict[str, float]:
    """{"median_m", "within_10m", "within_25m", "within_50m"} of (Q,) metre errors, as Python floats.

    The median is numpy's (the mean of the two middle values for an even Q); a share counts errors <= the
    threshold and lies in [0, 1].
    """
    e = np.asarray(errors, dtype=np.float64)
    if e.ndim != 1 or e.size == 0:
        raise ValueError(f"errors must be a non-empty 1-D array of metres, got shape {e.shape}")
    if not np.isfinite(e).all() or (e < 0).any():
        i = int(np.flatnonzero(~np.isfinite(e) | (e < 0))[0])
        raise ValueError(f"errors must be finite and >= 0 metres; entry {i} is {e[i]}")
    out = {"median_m": float(np.median(e))}
    out.update({f"within_{t}m": float((e <= t).mean()) for t in THRESHOLDS_M})
    return out
