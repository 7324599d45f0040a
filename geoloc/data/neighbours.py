"""Nearest-neighbour lists of training pairs, for the hard-batch samplers (geoloc.data.samplers).

Row i lists other training pairs, nearest first, never one with pair i's own label (the same reference place):
- `gps_neighbour_lists`: by great-circle distance between the pairs' positions (precomputed once by a dataset);
- `descriptor_neighbour_lists`: by the similarity of query i's descriptor to the other places' reference
  descriptors, as Sample4Geo's similarity sampling (Deuser et al., ICCV 2023) does each epoch.
Both work on blocks of rows and keep only the top k of each, so memory stays bounded at N = 10^5.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from geoloc.data.geo import haversine_m

#: score-matrix elements computed at once: 32 MiB of float32 similarities; the haversine formula holds a few
#: float64 temporaries of its block, so GPS blocks are smaller
DESCRIPTOR_CHUNK = 2**23
GPS_CHUNK = 2**21


def gps_neighbour_lists(latlon, k: int, labels=None, chunk_elements: int = GPS_CHUNK) -> np.ndarray:
    """(N, 2) (lat, lon) degrees of the training pairs -> (N, k) int64 pair indices, nearest first by haversine
    distance, leaving out pair i itself and every pair with label[i] (default: one label per pair). A row with
    fewer than k such pairs is padded with -1."""
    latlon = np.asarray(latlon, np.float64)
    if latlon.ndim != 2 or latlon.shape[1] != 2 or len(latlon) == 0:
        raise ValueError(f"gps_neighbour_lists takes an (N, 2) array of (lat, lon) degrees, got shape {latlon.shape}")
    if not np.isfinite(latlon).all():
        raise ValueError(f"gps_neighbour_lists: {int((~np.isfinite(latlon)).any(1).sum())} positions are not "
                         f"finite; give every training pair a position")
    n = len(latlon)
    labels = _labels(labels, n, "gps_neighbour_lists")

    def distances(rows: slice) -> torch.Tensor:
        block = torch.from_numpy(haversine_m(latlon[rows, None], latlon[None]))
        block[labels[rows, None] == labels[None]] = float("inf")  # own pair and its label's other pairs
        return block

    return _top_k(distances, n, n, k, largest=False, chunk_elements=chunk_elements).numpy()


def descriptor_neighbour_lists(query, reference, labels, k: int,
                               chunk_elements: int = DESCRIPTOR_CHUNK) -> np.ndarray:
    """query, reference: (N, D) descriptors of the training pairs in dataset order; labels (N,) their places.
    -> (N, k') int64 pair indices, k' = min(k, places - 1): the places whose reference descriptors have the
    highest dot product (cosine, for unit descriptors) with query i, best first, i's own place left out. A place
    with several pairs is scored once, by the reference descriptor of its first pair, which row i then names.
    Runs on the descriptors' device (torch tensors or numpy arrays)."""
    query, reference = _as_float_tensor(query, "query"), _as_float_tensor(reference, "reference")
    n = len(query)
    if reference.shape != query.shape or query.ndim != 2 or n == 0:
        raise ValueError(f"descriptor_neighbour_lists takes query and reference descriptors of the same (N, D) "
                         f"shape, got {tuple(query.shape)} and {tuple(reference.shape)}")
    reference = reference.to(query.device)
    labels = _labels(labels, n, "descriptor_neighbour_lists")
    _, first_pair, place = np.unique(labels, return_index=True, return_inverse=True)
    place_reference = reference[torch.from_numpy(first_pair).to(query.device)]
    own_place = torch.from_numpy(place.reshape(-1)).to(query.device)

    def similarity(rows: slice) -> torch.Tensor:
        block = query[rows] @ place_reference.T
        block[torch.arange(len(block), device=block.device), own_place[rows]] = float("-inf")
        return block

    places = len(first_pair)
    top_places = _top_k(similarity, n, places, min(k, places - 1), largest=True, chunk_elements=chunk_elements)
    top_places = top_places.numpy()
    return np.where(top_places >= 0, first_pair[top_places], -1).astype(np.int64)


def _top_k(scores: Callable[[slice], torch.Tensor], rows: int, cols: int, k: int, largest: bool,
           chunk_elements: int) -> torch.Tensor:
    """Row-wise top k of a rows x cols score matrix built `scores(rows)` a block of rows at a time; masked
    entries (+inf when smallest, -inf when largest) come back as -1. -> (rows, k) int64 on the CPU."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
        raise ValueError(f"the number of neighbours k must be an integer >= 0, got {k!r}")
    k = int(k)
    out = torch.full((rows, k), -1, dtype=torch.int64)
    if k == 0:
        return out
    step = max(1, chunk_elements // max(cols, 1))
    masked = float("-inf") if largest else float("inf")
    for start in range(0, rows, step):
        block = scores(slice(start, min(start + step, rows)))
        value, index = torch.topk(block, min(k, cols), dim=1, largest=largest, sorted=True)
        index[value == masked] = -1
        out[start:start + len(block), :index.shape[1]] = index.cpu()
    return out


def _labels(labels, n: int, who: str) -> np.ndarray:
    if labels is None:
        return np.arange(n)
    labels = np.asarray(labels)
    if labels.shape != (n,) or not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"{who}: labels must be ({n},) integers, one place id per training pair; got "
                         f"{labels.dtype} of shape {labels.shape}")
    return labels


def _as_float_tensor(x, name: str) -> torch.Tensor:
    x = x.detach() if isinstance(x, torch.Tensor) else torch.from_numpy(np.asarray(x))
    x = x.float()
    if not torch.isfinite(x).all():
        raise ValueError(f"{name} descriptors hold {int((~torch.isfinite(x)).any(-1).sum())} rows with NaN/inf; "
                         f"the model diverged or the extraction is wrong")
    return x
