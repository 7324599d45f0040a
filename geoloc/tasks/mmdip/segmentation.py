"""Phase 1 of MMDIP: static semantic segmentation from the dynamic image (ERFNet, or the FCN / U-Net baselines).

Loss: cross-entropy weighted by eq. 1's w_c = 1/ln(r_c + 1.02), r_c the training set's class fractions.
Validation scores one confusion matrix over all validation pixels (Table I); `best.pt` follows MIoU.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from geoloc.engine import Task
from geoloc.eval.segmentation import scores_from_confusion
from geoloc.losses.segmentation import class_weights
from geoloc.tasks.mmdip.mmdip_config import SegmentationConfig
from geoloc.tasks.mmdip.networks import build_segmenter


def batch_confusion(pred: torch.Tensor, target: torch.Tensor, k: int) -> torch.Tensor:
    """Per-sample confusion matrices B x K x K (rows target, cols prediction) of B x H x W label maps."""
    b = pred.shape[0]
    offset = torch.arange(b, device=pred.device).view(b, 1, 1) * k * k
    flat = (offset + target * k + pred).flatten()
    return torch.bincount(flat, minlength=b * k * k).view(b, k, k)


def confusion_metrics(confusion: torch.Tensor) -> dict[str, float]:
    scores = scores_from_confusion(confusion.sum(0).cpu().numpy())
    per_class = scores.pop("per_class_IoU")
    scores.update({f"IoU_{c}": v for c, v in enumerate(per_class) if v == v})  # NaN: class absent
    return scores


class SegmentationTask(Task):
    monitor = "MIoU"

    def __init__(self, cfg: SegmentationConfig, num_classes: int, fractions):
        super().__init__()
        self.cfg, self.num_classes = cfg, num_classes
        self.seg = build_segmenter(cfg, num_classes)
        self.register_buffer("class_weights", class_weights(fractions, cfg.class_weight_formula))

    def configure_optimizers(self):
        return [torch.optim.Adam(self.seg.parameters(), lr=self.cfg.lr)], []

    def training_step(self, batch, engine):
        logits = self.seg(batch["dynamic"])
        loss = F.cross_entropy(logits.float(), batch["label"], weight=self.class_weights)
        return {"loss": loss}

    def validation_step(self, batch):
        pred = self.seg(batch["dynamic"]).argmax(1)
        return {"confusion": batch_confusion(pred, batch["label"], self.num_classes), "index": batch["index"]}

    def validation_epoch_end(self, outputs):
        return confusion_metrics(outputs["confusion"])
