"""InfoNCE for queries of any field of view and unknown heading, on the extra query views of
geoloc/tasks/crossview/view_pairs.py (`views=any_view`: the window at a wrong bearing, the full panorama).

With q_i the limited view at its true bearing, w_i the same view at a wrong bearing, f_i the full panorama (all
through the query branch) and r_i the aerial reference, L2-normalised, t the temperature:

    L = 1/2 [CE_i(q_i · R / t) + CE_i(r_i · [Q; W] / t)]         the pair, with every wrong placement a negative
        + w_full · InfoNCE(F, R) + w_consistency · InfoNCE(Q, F)   ConGeo (Mi et al., ECCV 2024)

CE_i(x) is the cross-entropy of row x with target i, over the columns kept: another pair of the same place is left
out (as in `info_nce`), but every w_j is a negative, its own place's included. At evaluation the heading is searched
(score = max over candidate headings), so a view placed at a wrong bearing must score below the true placement:
the second term trains exactly that. InfoNCE is the symmetric loss of geoloc/losses/infonce.py.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from geoloc.losses.infonce import InfoNCELoss, info_nce
from geoloc.registry import register

__all__ = ["AnyViewInfoNCE", "heading_contrast"]


def heading_contrast(query: torch.Tensor, reference: torch.Tensor, wrong: torch.Tensor, temperature,
                     labels: torch.Tensor | None = None) -> torch.Tensor:
    """1/2 [mean_i CE(q_i · R / t, i) + mean_i CE(r_i · [Q; W] / t, i)], a 0-d tensor.

    query, reference, wrong: B×D (wrong[i]: query i's view at a wrong bearing); labels (B,): pairs of one place
    other than i are left out of row i's softmax, the wrong views never are."""
    query, reference, wrong = (F.normalize(x.float(), dim=1) for x in (query, reference, wrong))
    b = query.shape[0]
    eye = torch.eye(b, dtype=torch.bool, device=query.device)
    keep = eye | (labels[:, None] != labels[None, :]) if labels is not None else torch.ones_like(eye)
    forward = (query @ reference.t() / temperature).masked_fill(~keep, float("-inf"))
    backward = torch.cat([reference @ query.t(), reference @ wrong.t()], 1) / temperature
    backward = backward.masked_fill(~torch.cat([keep.t(), torch.ones_like(keep)], 1), float("-inf"))
    target = torch.arange(b, device=query.device)
    return (F.cross_entropy(forward, target) + F.cross_entropy(backward, target)) / 2


class AnyViewInfoNCE(InfoNCELoss):
    """The module docstring's L, with InfoNCELoss's temperature (fixed or learned) and label smoothing (on the
    InfoNCE terms)."""

    needs = ("query_views",)  # the task passes the extra views' descriptors (B×V×D) as `query_views`

    def __init__(self, temperature: float = 0.07, learn_temperature: bool = True, label_smoothing: float = 0.1,
                 full_weight: float = 1.0, consistency_weight: float = 1.0):
        super().__init__(temperature, learn_temperature, label_smoothing)
        self.full_weight, self.consistency_weight = full_weight, consistency_weight

    def forward(self, query, reference, labels=None, query_views=None):
        if query_views is None or query_views.ndim != 3 or query_views.shape[1] != 2 \
                or query_views.shape[0] != query.shape[0]:
            raise ValueError("loss any_view_infonce needs the two extra query views of views=any_view (B x 2 x D: "
                             "the window at a wrong bearing, the full panorama), one per query of the batch; got "
                             f"{None if query_views is None else tuple(query_views.shape)} for {query.shape[0]} "
                             "queries (one process only: the extra views are not gathered over ranks)")
        t = self.temperature
        wrong, full = query_views[:, 0], query_views[:, 1]
        pair = heading_contrast(query, reference, wrong, t, labels)
        full_term = info_nce(full, reference, t, labels, self.label_smoothing)
        consistency = info_nce(query, full, t, labels, self.label_smoothing)
        loss = pair + self.full_weight * full_term + self.consistency_weight * consistency
        return {"loss": loss, "pair": pair.detach(), "full": full_term.detach(), "consistency": consistency.detach()}


@register("loss", "any_view_infonce")
def any_view_infonce(temperature: float = 0.07, learn_temperature: bool = True, label_smoothing: float = 0.1,
                     full_weight: float = 1.0, consistency_weight: float = 1.0) -> AnyViewInfoNCE:
    """InfoNCE whose negatives include each query's window at a wrong bearing, plus ConGeo's full-view and
    consistency terms (weights full_weight, consistency_weight; 0 turns a term off)."""
    if not 0.0 <= label_smoothing < 1.0:
        raise ValueError(f"loss.label_smoothing must be in [0, 1), got {label_smoothing}")
    if full_weight < 0 or consistency_weight < 0:
        raise ValueError(f"loss.full_weight and loss.consistency_weight must be >= 0, got {full_weight} and "
                         f"{consistency_weight}")
    return AnyViewInfoNCE(temperature, learn_temperature, label_smoothing, full_weight, consistency_weight)
