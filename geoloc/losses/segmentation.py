"""Class-balanced weights for the static-segmentation cross-entropy (MMDIP eq. 1, the ENet formula).

`paper` (default): w_c = 1 / ln(r_c + 1 + 0.02), eq. 1 as published, r_c the class's pixel fraction in [0, 1].
   Weights range from 1/ln(1.02) = 50.5 (absent class) to 1/ln(2.02) = 1.42 (a class covering everything).
`authors`: w_c = 1 / ln(100 r_c + 1.02), the variant in the authors' code (r_c read as a percentage). It damps
   frequent classes much harder (w = 0.22 at r_c = 1).
The default is the published equation, because it is what the paper states and it keeps weights bounded in
[1.42, 50.5]; pick `authors` to reproduce their code.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

FORMULAS = ("paper", "authors")


def class_weights(fractions: Sequence[float], formula: str = "paper") -> torch.Tensor:
    """Per-class weights (float32 tensor) from the training set's class pixel fractions."""
    r = torch.as_tensor(list(fractions), dtype=torch.float64)
    if r.ndim != 1 or len(r) == 0:
        raise ValueError("class fractions must be a non-empty 1-D sequence")
    if (r < 0).any() or (r > 1).any() or not math.isclose(float(r.sum()), 1.0, abs_tol=1e-3):
        raise ValueError(f"class fractions must lie in [0, 1] and sum to 1, got {r.tolist()}")
    if formula == "paper":
        w = 1.0 / torch.log(r + 1.0 + 0.02)
    elif formula == "authors":
        w = 1.0 / torch.log(100.0 * r + 1.02)
    else:
        raise ValueError(f"unknown class-weight formula {formula!r}; choose one of {FORMULAS}")
    return w.float()
