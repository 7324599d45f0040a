"""Segmentation scores from one confusion matrix: PA, MPA, MIoU, FWIoU and per-class IoU (MMDIP Table I).

With the confusion matrix cm[target, pred] over all pixels, n = cm.sum(), t_c = cm[c, :].sum() (target pixels)
and p_c = cm[:, c].sum() (predicted pixels):
  PA = trace(cm) / n;  acc_c = cm[c, c] / t_c;  IoU_c = cm[c, c] / (t_c + p_c - cm[c, c]);
  MPA = mean acc_c;  MIoU = mean IoU_c;  FWIoU = sum_c (t_c / n) IoU_c.
A class absent from both target and prediction is left out of the means (its IoU is NaN). A class predicted but
absent from the target has acc_c = 0 (all of its predictions are wrong), so it counts against MPA.
"""

from __future__ import annotations

import numpy as np
import torch


def _as_numpy(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def confusion_matrix(pred, target, num_classes: int) -> np.ndarray:
    """num_classes x num_classes int64 counts, rows = target, cols = prediction. Values must lie in the class set."""
    pred, target = _as_numpy(pred).ravel(), _as_numpy(target).ravel()
    if pred.shape != target.shape:
        raise ValueError(f"pred and target differ in size: {pred.size} vs {target.size}")
    for name, x in (("pred", pred), ("target", target)):
        if x.size and (x.min() < 0 or x.max() >= num_classes):
            raise ValueError(f"{name} holds labels outside [0, {num_classes}): [{x.min()}, {x.max()}]")
    flat = target.astype(np.int64) * num_classes + pred.astype(np.int64)
    return np.bincount(flat, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def scores_from_confusion(cm: np.ndarray) -> dict:
    """PA, MPA, MIoU, FWIoU (floats) and per_class_IoU (list, NaN for classes absent from both)."""
    cm = np.asarray(cm, dtype=np.float64)
    n = cm.sum()
    if n == 0:
        raise ValueError("empty confusion matrix")
    tp = np.diag(cm)
    t, p = cm.sum(1), cm.sum(0)
    present = (t + p) > 0
    union = t + p - tp
    iou = np.full(len(cm), np.nan)
    iou[present] = tp[present] / union[present]
    acc = np.divide(tp, t, out=np.zeros_like(tp), where=t > 0)
    return {
        "PA": float(tp.sum() / n),
        "MPA": float(acc[present].mean()),
        "MIoU": float(iou[present].mean()),
        "FWIoU": float(np.sum((t / n)[present] * iou[present])),
        "per_class_IoU": iou.tolist(),
    }


def segmentation_scores(pred, target, num_classes: int) -> dict:
    """Scores of integer label maps `pred` and `target` (any equal shapes) over all the pixels given."""
    return scores_from_confusion(confusion_matrix(pred, target, num_classes))
