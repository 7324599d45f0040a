"""Symmetric InfoNCE over a batch of matching pairs (CLIP, Radford et al. 2021; Sample4Geo, Deuser et al. ICCV 2023).

    logits = q r^T / t on L2-normalised rows; loss = (CE over rows + CE over columns) / 2, target = the diagonal.

With place labels, an off-diagonal pair that shares the diagonal's label is another view of the same place, so it is
left out of the softmax instead of being pushed away as a negative. Label smoothing follows torch's definition
(a share `label_smoothing` of the target spread evenly over the classes of the softmax), restricted to the classes
that remain in it.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from geoloc.registry import register

__all__ = ["InfoNCELoss", "info_nce"]


def info_nce(query: torch.Tensor, reference: torch.Tensor, temperature: float | torch.Tensor = 0.1,
             labels: torch.Tensor | None = None, label_smoothing: float = 0.0) -> torch.Tensor:
    """Symmetric InfoNCE, a 0-d tensor.

    Args:
        query: B x D street descriptors; reference: B x D aerial descriptors, ``reference[i]`` matches
            ``query[i]``. Rows are L2-normalised here (a no-op for the networks' normalised outputs).
        temperature: t > 0, a float or a 0-d tensor (a learned one keeps its gradient).
        labels: (B,) place ids; pairs (i, j != i) with labels[i] == labels[j] are no negatives.
        label_smoothing: in [0, 1).
    """
    if query.ndim != 2 or query.shape != reference.shape:
        raise ValueError(f"query and reference must both be B x D, got {tuple(query.shape)} and "
                         f"{tuple(reference.shape)}")
    if not 0.0 <= label_smoothing < 1.0:
        raise ValueError(f"label_smoothing must be in [0, 1), got {label_smoothing}")
    t = float(temperature.detach()) if isinstance(temperature, torch.Tensor) else float(temperature)
    if t <= 0:
        raise ValueError(f"temperature must be > 0, got {t}")
    query, reference = F.normalize(query.float(), dim=1), F.normalize(reference.float(), dim=1)
    logits = query @ reference.t() / temperature  # [i, j]: query i against reference j
    b = logits.shape[0]
    keep = torch.ones(b, b, dtype=torch.bool, device=logits.device)
    if labels is not None:
        if labels.shape != (b,):
            raise ValueError(f"labels must have shape ({b},), got {tuple(labels.shape)}")
        same_place = labels[:, None] == labels[None, :]
        keep = ~same_place | torch.eye(b, dtype=torch.bool, device=logits.device)
    return (_cross_entropy(logits, keep, label_smoothing) + _cross_entropy(logits.t(), keep.t(), label_smoothing)) / 2


def _cross_entropy(logits: torch.Tensor, keep: torch.Tensor, smoothing: float) -> torch.Tensor:
    """Mean over rows of CE with the diagonal as target, over the kept columns only."""
    log_p = torch.log_softmax(logits.masked_fill(~keep, float("-inf")), dim=1)
    log_p = log_p.masked_fill(~keep, 0.0)  # dropped columns take no part, not even in the smoothing
    nll = -log_p.diagonal()
    if smoothing == 0.0:
        return nll.mean()
    uniform = -log_p.sum(dim=1) / keep.sum(dim=1)
    return ((1 - smoothing) * nll + smoothing * uniform).mean()


class InfoNCELoss(nn.Module):
    """`info_nce` with a fixed or a learned temperature, learned as log(1/t) (CLIP's logit scale).

    A learned temperature is a parameter of this module, so the task's optimizer must include it."""

    def __init__(self, temperature: float = 0.07, learn_temperature: bool = False, label_smoothing: float = 0.0):
        super().__init__()
        if temperature <= 0:
            raise ValueError(f"loss.temperature must be > 0, got {temperature}")
        self.label_smoothing = label_smoothing
        scale = torch.tensor(math.log(1.0 / temperature))
        if learn_temperature:
            self.log_inv_temperature = nn.Parameter(scale)
        else:
            self.register_buffer("log_inv_temperature", scale)

    @property
    def temperature(self) -> torch.Tensor:
        return torch.exp(-self.log_inv_temperature)

    def forward(self, query: torch.Tensor, reference: torch.Tensor, labels: torch.Tensor | None = None):
        return info_nce(query, reference, self.temperature, labels, self.label_smoothing)


@register("loss", "infonce")
def infonce(temperature: float = 0.07, learn_temperature: bool = True, label_smoothing: float = 0.1) -> InfoNCELoss:
    """Sample4Geo's loss: symmetric InfoNCE, temperature learned from 0.07 (CLIP), label smoothing 0.1."""
    if not 0.0 <= label_smoothing < 1.0:
        raise ValueError(f"loss.label_smoothing must be in [0, 1), got {label_smoothing}")
    return InfoNCELoss(temperature, learn_temperature, label_smoothing)
