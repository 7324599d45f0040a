"""Weighted soft-margin triplet loss, exhaustive over the batch (CVM-Net, Hu et al. CVPR 2018; SAFA, Shi et al.
NeurIPS 2019), as used by the multi-scale attention encoder paper (Li et al., CAAI TIT 2023)."""
from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["soft_margin_triplet"]


def soft_margin_triplet(
    query: torch.Tensor,
    reference: torch.Tensor,
    alpha: float = 10.0,
    extra_negatives: torch.Tensor | None = None,
    extra_mask: torch.Tensor | None = None,
    labels: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean of log(1 + exp(alpha * (d_pos - d_neg))) over every triplet, with d = ||a - b||^2 = 2 - 2 a.b.

    Args:
        query: B x D street descriptors, L2-normalised rows.
        reference: B x D aerial descriptors, L2-normalised rows; ``reference[i]`` matches ``query[i]``.
        alpha: the weight of the soft margin (10 in CVM-Net / SAFA / the paper).
        extra_negatives: Q x D extra reference negatives (the GMS queue), used for the query -> reference
            direction only: one term per (query, extra negative) pair.
        extra_mask: B x Q bool, True = keep the term (False drops e.g. same-location or empty queue slots).
        labels: (B,) place labels. Two pairs of the same place (e.g. two VIGOR panoramas whose positive is the same
            tile) are not each other's negatives: their in-batch terms are left out. With distinct labels (the
            one-to-one datasets) nothing is left out and the result is the unlabelled one, bit for bit.

    In the batch, both directions count for every ordered pair i != j: the query anchor i against reference
    negative j, and the reference anchor i against query negative j; 2B(B-1) terms. The result is the mean over
    all kept terms (a 0-d tensor), and 0 when there is none (B = 1 and no extra negative).
    Half-precision inputs are computed in float32.
    """
    if query.ndim != 2 or query.shape != reference.shape:
        raise ValueError(f"query and reference must both be B x D, got {tuple(query.shape)} and "
                         f"{tuple(reference.shape)}")
    if query.dtype in (torch.float16, torch.bfloat16):
        query, reference = query.float(), reference.float()
    b = query.shape[0]

    dist = 2 - 2 * query @ reference.t()  # dist[i, j] = d(query i, reference j)
    d_pos = dist.diagonal()
    negative = ~torch.eye(b, dtype=torch.bool, device=dist.device)
    count = 2 * b * (b - 1)
    if labels is not None:
        if labels.shape != (b,):
            raise ValueError(f"labels must have shape ({b},), got {tuple(labels.shape)}")
        if labels.unique().numel() < b:  # only then is anything left out (and the 1:1 path stays as it was)
            negative = negative & (labels[:, None] != labels[None, :]).to(dist.device)
            count = 2 * int(negative.sum())
    q_to_r = F.softplus(alpha * (d_pos[:, None] - dist))[negative]  # query anchor i, reference negative j
    r_to_q = F.softplus(alpha * (d_pos[None, :] - dist))[negative]  # reference anchor j, query negative i
    total = q_to_r.sum() + r_to_q.sum()

    if extra_negatives is not None:
        if extra_negatives.ndim != 2 or extra_negatives.shape[1] != query.shape[1]:
            raise ValueError(f"extra_negatives must be Q x {query.shape[1]}, got {tuple(extra_negatives.shape)}")
        extra_dist = 2 - 2 * query @ extra_negatives.to(query.dtype).t()
        terms = F.softplus(alpha * (d_pos[:, None] - extra_dist))
        if extra_mask is None:
            total, count = total + terms.sum(), count + terms.numel()
        else:
            if extra_mask.shape != terms.shape or extra_mask.dtype != torch.bool:
                raise ValueError(f"extra_mask must be a bool tensor of shape {tuple(terms.shape)}, got "
                                 f"{extra_mask.dtype} {tuple(extra_mask.shape)}")
            # where() rather than indexing keeps the shapes static and the masked terms out of the gradient.
            total = total + torch.where(extra_mask, terms, torch.zeros_like(terms)).sum()
            count = count + extra_mask.sum()
    elif extra_mask is not None:
        raise ValueError("extra_mask given without extra_negatives")

    if isinstance(count, int):
        return total / count if count else total * 0
    return total / count.clamp(min=1)
