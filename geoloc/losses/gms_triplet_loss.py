"""The paper's loss as a plug-in: the weighted soft-margin triplet with the GMS global hard-negative queue.

Li, Tu, Chen, Yu, "Multi-scale attention encoder for street-to-aerial image geo-localization" (CAAI TIT 2023):
alpha 10 and a fixed-length queue of reference descriptors (0 = the "w/o GMS" row). The paper gives no length: the
default 1,024 (the paper configs') is geoloc's choice. Formulas: geoloc/losses/triplet.py and gms_queue.py;
docs/conventions.md "Soft-margin triplet" and "GMS queue".
"""

from __future__ import annotations

import torch
from torch import nn

from geoloc.engine import distributed as dist
from geoloc.losses.gms_queue import GMSQueue
from geoloc.losses.triplet import soft_margin_triplet
from geoloc.registry import register


@register("loss", "gms_triplet")
class GMSTripletLoss(nn.Module):
    """loss(query, reference, labels) on the batch gathered over ranks (B×D each, labels (B,)) -> {"loss", ...}.

    The queue holds descriptors of earlier steps. While the network still moves fast they are stale, and as their
    terms outnumber the in-batch ones (B x queue_size vs 2B(B-1)) they can swamp the loss: moving every descriptor
    away from the old entries, down to a collapse onto one point, pays more than learning places (seen on the
    synthetic default, R@1 near chance). Hence `queue_start_epoch`, as in cross-batch memory (Wang et al., CVPR
    2020), which starts its memory once the embedding drifts slowly.
    """

    def __init__(self, dim: int, alpha: float = 10.0, queue_size: int = 1024, queue_start_epoch: int = 0):
        super().__init__()
        if alpha <= 0:
            raise ValueError(f"loss.alpha must be > 0, got {alpha}")
        if queue_size < 0:
            raise ValueError(f"loss.queue_size must be >= 0, got {queue_size}")
        if queue_start_epoch < 0:
            raise ValueError(f"loss.queue_start_epoch must be >= 0, got {queue_start_epoch}")
        self.alpha, self.queue_size, self.queue_start_epoch = alpha, queue_size, queue_start_epoch
        self.queue = GMSQueue(queue_size, dim)
        self.epoch = 0
        self._push = None

    def on_train_epoch_start(self, epoch: int) -> None:
        self.epoch = epoch

    def forward(self, query: torch.Tensor, reference: torch.Tensor, labels: torch.Tensor) -> dict:
        use_queue = self.queue_size > 0 and self.epoch >= self.queue_start_epoch
        extra, mask = self.queue.negatives(labels) if use_queue else (None, None)
        loss = soft_margin_triplet(query, reference, alpha=self.alpha, extra_negatives=extra, extra_mask=mask,
                                   labels=labels)
        if use_queue and self.training:
            # this rank's queries' hardest in-batch negatives; push() gathers them over ranks, after the step
            hard, hard_labels = self.queue.hardest_negatives(query.detach(), reference.detach(), labels)
            local = query.shape[0] // dist.world_size()
            lo = dist.rank() * local
            self._push = (hard[lo : lo + local], hard_labels[lo : lo + local])
        return {"loss": loss}

    def on_train_batch_end(self) -> None:
        if self._push is not None:
            self.queue.push(*self._push)
            self._push = None
