"""What every recall path asks of descriptors before it reports a number.

- Finite: a NaN compares false, so a NaN descriptor is never "strictly closer" than anything and its query would
  count as a hit. Non-finite rows raise, naming query or reference and how many rows.
- Unit length: ranking is by inner product, which equals d = 2 - 2 a.b (docs/conventions.md "Descriptors") only
  for L2-normalised rows. Rows whose norm is off by more than ``UNIT_TOLERANCE`` are L2-normalised (cosine
  ranking); rows already unit length are used exactly as given, so normalised descriptors give bit for bit the
  numbers they gave before. An all-zero row has no direction and raises.
- Not collapsed: ties count in the query's favour, so a network mapping every image to one point would score
  R@1 = 100%. When the reference spread (sum over dimensions of the standard deviation) is below
  ``COLLAPSE_SPREAD``, every metric reports its worst value with a warning (`geoloc.eval.keys.guarded`).

`checked_pair` is what every scorer path (`geoloc.eval.scoring`, the FAISS backend, the gallery index) takes its
descriptors through; `check_descriptors` gives validation and the gallery paths the reference spread.
"""
from __future__ import annotations

import numpy as np
import torch

from geoloc.data.relevance import Relevance

__all__ = ["COLLAPSE_SPREAD", "UNIT_TOLERANCE", "as_float_tensor", "check_descriptors", "checked_pair",
           "descriptor_spread", "require_finite", "unit_rows"]

UNIT_TOLERANCE = 1e-3  # above float32 rounding at any dimension, and fp16/bf16 outputs get re-normalised
COLLAPSE_SPREAD = 1e-4


def as_float_tensor(x, name: str, ndims: tuple[int, ...] = (2,)) -> torch.Tensor:
    """numpy array or tensor -> floating tensor (float64 stays float64; anything else becomes float32), detached.

    ``ndims``: the accepted numbers of dimensions (2: N x D; 3: Q x K x D, K candidates per query)."""
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(x)
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch tensor or a numpy array, got {type(x).__name__}")
    if x.ndim not in ndims:
        shapes = " or ".join({2: "N x D", 3: "Q x K x D"}[n] for n in ndims)
        raise ValueError(f"{name} must be {shapes}, got shape {tuple(x.shape)}")
    if not x.is_floating_point():
        x = x.float()
    return x.detach()


def checked_pair(query, reference, one_to_one: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """(query, reference) as unit rows of one floating dtype, the query on the reference's device.

    query: Q x D or Q x K x D (K candidates of each query, each candidate a row); reference: N x D. Tensors or
    numpy arrays. Raises on empty or mismatched inputs (``one_to_one``: fewer references than queries), then on
    non-finite or all-zero rows (`unit_rows`)."""
    q = as_float_tensor(query, "query", ndims=(2, 3))
    r = as_float_tensor(reference, "reference")
    if q.shape[0] == 0 or r.shape[0] == 0 or q.shape[1:-1].numel() == 0:
        raise ValueError(f"empty descriptors: query {tuple(q.shape)}, reference {tuple(r.shape)}")
    if q.shape[-1] != r.shape[1]:
        raise ValueError(f"query and reference dimensions differ: {q.shape[-1]} vs {r.shape[1]}")
    if one_to_one:
        Relevance.one_to_one(q.shape[0], r.shape[0])  # raises when a query has no reference of its own
    dtype = torch.promote_types(q.dtype, r.dtype)
    q = q.to(r.device, dtype)
    flat = unit_rows(q.reshape(-1, q.shape[-1]), "query")
    return flat.reshape(q.shape), unit_rows(r.to(dtype), "reference")


def _norms(x: torch.Tensor) -> torch.Tensor:
    # A row reduction: no N x D temporary, whatever the gallery size.
    return torch.linalg.vector_norm(x, dim=1)


def _first_rows(mask: torch.Tensor, show: int = 5) -> list[int]:
    return torch.nonzero(mask).flatten()[:show].tolist()


def require_finite(x: torch.Tensor, name: str, norms: torch.Tensor | None = None) -> None:
    """Raise FloatingPointError if any row of the N x D tensor ``x`` holds NaN or inf."""
    norms = _norms(x) if norms is None else norms
    bad = ~torch.isfinite(norms)  # a NaN or inf anywhere in a row makes its norm non-finite
    if bad.any():
        raise FloatingPointError(
            f"{int(bad.sum())} of {x.shape[0]} {name} descriptors hold NaN/inf (rows {_first_rows(bad)}...): "
            "recall would count them as hits. The network diverged or its input is broken; lower optim.lr, set "
            "trainer.grad_clip, or evaluate an earlier checkpoint.")


def unit_rows(x: torch.Tensor, name: str) -> torch.Tensor:
    """``x`` (N x D, floating) with every row of unit L2 norm; raises on non-finite or all-zero rows.

    Returns ``x`` itself when every row is already unit length within ``UNIT_TOLERANCE``; otherwise a copy in
    which the rows off by more than that are divided by their norm.
    """
    norms = _norms(x)
    require_finite(x, name, norms)
    zero = norms == 0
    if zero.any():
        raise ValueError(f"{int(zero.sum())} of {x.shape[0]} {name} descriptors are all zeros (rows "
                         f"{_first_rows(zero)}...): a zero vector has no direction to rank by")
    off = (norms - 1).abs() > UNIT_TOLERANCE
    if not off.any():
        return x
    x = x.clone()
    x[off] = x[off] / norms[off, None]
    return x


def descriptor_spread(x: torch.Tensor) -> float:
    """Sum over dimensions of the per-dimension standard deviation of the rows of ``x``: 0 for a collapse."""
    return float(x.float().std(dim=0).sum())


def check_descriptors(query: torch.Tensor, reference: torch.Tensor | None = None) -> float | None:
    """Raise on non-finite query or reference rows; return the reference spread (None without references)."""
    require_finite(query, "query")
    if reference is None:
        return None
    require_finite(reference, "reference")
    return descriptor_spread(reference)
