"""The cross-view geo-localization task: MSAE Siamese + weighted soft-margin triplet + GMS queue.

Li, Tu, Chen, Yu, "Multi-scale attention encoder for street-to-aerial image geo-localization" (CAAI TIT 2023).
Paper settings: Adam lr 1e-4 (betas 0.9/0.999), StepLR /10 every 80 epochs, 100 epochs, batch 64, alpha 10.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from geoloc.config import require_name
from geoloc.engine import Task
from geoloc.engine import distributed as dist
from geoloc.eval import recall_at_k
from geoloc.eval.descriptors import check_descriptors, guarded_recall
from geoloc.losses import GMSQueue, soft_margin_triplet
from geoloc.models.crossview import CrossViewModel, CrossViewModelConfig


@dataclass
class TripletLossConfig:
    name: str = "gms_triplet"
    alpha: float = 10.0  # soft-margin scale (CVM-Net / SAFA)
    queue_size: int = 1024  # GMS global hard-negative queue length; 0 = "w/o GMS"
    queue_start_epoch: int = 0  # the queue is filled and used from this epoch on (warm-up against feature drift)

    def __post_init__(self):
        require_name("loss", self.name, ("gms_triplet",))
        if self.alpha <= 0:
            raise ValueError(f"loss.alpha must be > 0, got {self.alpha}")
        if self.queue_size < 0:
            raise ValueError(f"loss.queue_size must be >= 0, got {self.queue_size}")
        if self.queue_start_epoch < 0:
            raise ValueError(f"loss.queue_start_epoch must be >= 0, got {self.queue_start_epoch}")


@dataclass
class OptimConfig:
    name: str = "adam"
    lr: float = 1e-4
    betas: tuple[float, float] = (0.9, 0.999)
    weight_decay: float = 0.0
    step_size: int = 80  # StepLR period in epochs
    gamma: float = 0.1

    def __post_init__(self):
        require_name("optim", self.name, ("adam",))
        if self.lr <= 0:
            raise ValueError(f"optim.lr must be > 0, got {self.lr}")
        if self.step_size < 1:
            raise ValueError(f"optim.step_size must be >= 1, got {self.step_size}")


class CrossViewTask(Task):
    monitor = "R@1"

    def __init__(self, model: CrossViewModelConfig, loss: TripletLossConfig, optim: OptimConfig):
        super().__init__()
        self.model_cfg, self.loss_cfg, self.optim_cfg = model, loss, optim
        self.model = CrossViewModel(model)
        self.queue = GMSQueue(loss.queue_size, model.dim)

    def configure_optimizers(self):
        opt = torch.optim.Adam(self.model.parameters(), lr=self.optim_cfg.lr, betas=tuple(self.optim_cfg.betas),
                               weight_decay=self.optim_cfg.weight_decay)
        sched = torch.optim.lr_scheduler.StepLR(opt, step_size=self.optim_cfg.step_size, gamma=self.optim_cfg.gamma)
        return [opt], [sched]

    def training_step(self, batch, engine):
        query, reference = self.model(batch["query"], batch["reference"])
        query, reference = query.float(), reference.float()
        # the exhaustive loss sees the global batch; gradients flow back to every rank's slice
        query_all = dist.all_gather_with_grad(query)
        reference_all = dist.all_gather_with_grad(reference)
        ids_all = dist.all_gather_nograd(batch["index"])
        # The queue holds descriptors of earlier steps. While the network still moves fast they are stale, and as
        # their terms outnumber the in-batch ones (B x queue_size vs 2B(B-1)) they can swamp the loss: moving every
        # descriptor away from the old entries, down to a collapse onto one point, pays more than learning places
        # (seen on the synthetic default, R@1 near chance). Hence the warm-up, as in cross-batch memory (Wang et
        # al., CVPR 2020), which starts its memory once the embedding drifts slowly.
        use_queue = self.loss_cfg.queue_size > 0 and engine.epoch >= self.loss_cfg.queue_start_epoch
        extra, mask = (None, None)
        if use_queue:
            extra, mask = self.queue.negatives(ids_all)
        loss = soft_margin_triplet(query_all, reference_all, alpha=self.loss_cfg.alpha,
                                   extra_negatives=extra, extra_mask=mask)
        out = {"loss": loss}
        if use_queue:
            # this rank's queries' hardest in-batch negatives; push() gathers them over ranks (after the loss)
            hard, hard_ids = self.queue.hardest_negatives(query_all.detach(), reference_all.detach(), ids_all)
            lo = dist.rank() * query.shape[0]
            out["push"] = (hard[lo : lo + query.shape[0]], hard_ids[lo : lo + query.shape[0]])
        return out

    def on_train_batch_end(self, outputs):
        if "push" in outputs:
            self.queue.push(*outputs["push"])

    def validation_step(self, batch):
        query, reference = self.model(batch["query"], batch["reference"])
        return {"query": query, "reference": reference, "index": batch["index"]}

    def validation_epoch_end(self, outputs):
        query, reference = outputs["query"], outputs["reference"]
        # Non-finite descriptors raise; a collapse (ties count in the query's favour, so one shared descriptor would
        # score R@1 = 100%) reports recall 0. The same checks guard the saved-gallery path (crossview_gallery).
        spread = check_descriptors(query, reference)
        return guarded_recall(lambda: recall_at_k(query, reference), spread)
