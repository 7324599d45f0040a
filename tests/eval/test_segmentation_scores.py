import numpy as np
import pytest
import torch
from geoloc.eval.segmentation import confusion_matrix, segmentation_scores


def loop_scores(pred, target, k):
    cm = np.zeros((k, k))
    for t, p in zip(target.ravel(), pred.ravel()):
        cm[t, p] += 1
    n = cm.sum()
    ious, accs, fw = [], [], 0.0
    for c in range(k):
        tp, t_c, p_c = cm[c, c], cm[c, :].sum(), cm[:, c].sum()
        if t_c + p_c == 0:
            continue
        iou = tp / (t_c + p_c - tp)
        ious.append(iou)
        accs.append(tp / t_c if t_c else 0.0)
        fw += t_c / n * iou
    return {"PA": np.trace(cm) / n, "MPA": np.mean(accs), "MIoU": np.mean(ious), "FWIoU": fw}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scores_match_confusion_loop(seed):
    rng = np.random.default_rng(seed)
    target = rng.integers(0, 6, size=(17, 23))  # classes 6, 7 absent from both
    pred = np.where(rng.random(target.shape) < 0.6, target, rng.integers(0, 7, size=target.shape))  # 6: pred only
    got = segmentation_scores(pred, target, 8)
    want = loop_scores(pred, target, 8)
    for key in want:
        assert got[key] == pytest.approx(want[key], abs=1e-12), key
    assert np.isnan(got["per_class_IoU"][7])
    assert got["per_class_IoU"][6] == 0.0


def test_perfect_prediction_and_tensor_input():
    target = torch.tensor([[0, 1], [2, 2]])
    s = segmentation_scores(target, target, 8)
    assert s["PA"] == s["MPA"] == s["MIoU"] == s["FWIoU"] == 1.0
    assert sum(np.isnan(s["per_class_IoU"])) == 5


def test_confusion_orientation_and_bad_labels():
    cm = confusion_matrix(np.array([1]), np.array([0]), 3)
    assert cm[0, 1] == 1  # rows are targets
    with pytest.raises(ValueError, match="outside"):
        confusion_matrix(np.array([3]), np.array([0]), 3)
    with pytest.raises(ValueError, match="differ"):
        confusion_matrix(np.zeros(3, int), np.zeros(4, int), 3)
