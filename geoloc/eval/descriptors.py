"""What every recall path asks of descriptors before it reports a number.

- Finite: a NaN compares false, so a NaN descriptor is never "strictly closer" than anything and its query would
  count as a hit. Non-finite rows raise, naming query or reference and how many rows.
- Unit length: ranking is by inner product, which equals d = 2 - 2 a.b (DESIGN.md) only for L2-normalised rows.
  Rows whose norm is off by more than ``UNIT_TOLERANCE`` are L2-normalised (cosine ranking); rows already unit
  length are used exactly as given, so normalised descriptors give bit for bit the numbers they gave before.
  An all-zero row has no direction and raises.
- Not collapsed: ties count in the query's favour, so a network mapping every image to one point would score
  R@1 = 100%. When the reference spread (sum over dimensions of the standard deviation) is below
  ``COLLAPSE_SPREAD`` the recall keys are reported as 0 with a warning.

`check_descriptors` and `guarded_recall` are the one place the validation and gallery paths take these checks from.
"""
from __future__ import annotations

import warnings
from typing import Callable, Iterable

import torch

__all__ = ["COLLAPSE_SPREAD", "UNIT_TOLERANCE", "check_descriptors", "descriptor_spread", "guarded_recall",
           "require_finite", "unit_rows"]

UNIT_TOLERANCE = 1e-3  # above float32 rounding at any dimension, and fp16/bf16 outputs get re-normalised
COLLAPSE_SPREAD = 1e-4


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


def guarded_recall(compute: Callable[[], dict], reference_spread: float, ks: Iterable[int] = (1, 5, 10),
                   collapsed: dict | None = None) -> dict:
    """``compute()``'s recall dict plus ``reference_spread``; on a collapse, R@K = 0 (or ``collapsed``, the worst
    value of every metric compute() would give) with a warning instead.

    ``compute`` is not called on a collapse (an all-zero collapse could not be ranked at all).
    """
    if reference_spread < COLLAPSE_SPREAD:
        warnings.warn(f"reference descriptors have collapsed (spread {reference_spread:.2e} < {COLLAPSE_SPREAD}): "
                      "every image maps to about one point, so recall is meaningless here and is reported as 0")
        metrics = dict(collapsed) if collapsed is not None else {**{f"R@{k}": 0.0 for k in ks}, "R@1%": 0.0}
    else:
        metrics = compute()
    metrics["reference_spread"] = reference_spread
    return metrics
