"""Segmentation class weights (MMDIP eq. 1) and where they act, the LSGAN losses, the VGG perceptual loss."""
import contextlib
import itertools
import math
from types import SimpleNamespace

import pytest
import torch
from geoloc.losses.gan import lsgan_d_loss, lsgan_g_loss
from geoloc.losses.perceptual import VGGPerceptualLoss, resolve_weights
from geoloc.losses.segmentation import class_weights
from geoloc.tasks.mmdip.mmdip_config import MMDIPConfig, SegmentationConfig, TranslationConfig
from geoloc.tasks.mmdip.joint import JointTask
from geoloc.tasks.mmdip.segmentation import SegmentationTask
from torchvision.models.vgg import cfgs, make_layers


def test_class_weights_paper_and_authors_formulas():
    r = [0.5, 0.3, 0.2, 0.0]
    paper = class_weights(r, "paper")
    authors = class_weights(r, "authors")
    for i, rc in enumerate(r):
        assert paper[i].item() == pytest.approx(1 / math.log(rc + 1 + 0.02), rel=1e-6)
        assert authors[i].item() == pytest.approx(1 / math.log(100 * rc + 1.02), rel=1e-6)
    assert torch.equal(class_weights(r), paper)  # the default is the published eq. 1
    assert paper[3].item() == pytest.approx(50.50, abs=0.01)


def test_class_weights_refuse_bad_input():
    with pytest.raises(ValueError, match="sum to 1"):
        class_weights([0.5, 0.2])
    with pytest.raises(ValueError, match="lie in"):
        class_weights([0.6, 0.5, -0.1])  # sums to 1, but a fraction is negative
    with pytest.raises(ValueError, match="non-empty 1-D sequence"):
        class_weights([])
    with pytest.raises(ValueError, match="non-empty 1-D sequence"):
        class_weights([[0.5, 0.5]])
    with pytest.raises(ValueError, match="unknown class-weight formula"):
        class_weights([1.0], "enet")
    # fractions rounded for a JSON file still sum to 1 closely enough
    assert class_weights([0.3333, 0.3333, 0.3333]).shape == (3,)


def test_lsgan_losses():
    ones, zeros = torch.ones(2, 1, 3, 3), torch.zeros(2, 1, 3, 3)
    assert lsgan_d_loss(ones, zeros).item() == 0.0
    assert lsgan_d_loss(zeros, ones).item() == 1.0
    assert lsgan_g_loss(ones).item() == 0.0
    assert lsgan_g_loss(torch.full((1, 1, 2, 2), 3.0)).item() == 4.0


def test_perceptual_loads_a_local_state_dict(tmp_path):
    torch.manual_seed(123)
    features = make_layers(cfgs["D"])  # exactly torchvision's vgg16().features, without the 120M classifier
    full = {f"features.{k}": v for k, v in features.state_dict().items()}
    full["classifier.6.bias"] = torch.zeros(1000)
    path = tmp_path / "vgg16.pth"
    torch.save(full, path)  # a torchvision-style full state dict
    loss = VGGPerceptualLoss(weights=str(path), layers=("relu1_2", "relu2_2"))
    assert torch.equal(loss.features[7].weight, features[7].weight)
    assert not any(p.requires_grad for p in loss.parameters())
    feats_only = tmp_path / "features.pth"
    torch.save(features.state_dict(), feats_only)  # a features-only state dict loads too
    assert torch.equal(VGGPerceptualLoss(str(feats_only), ("relu1_2",)).features[2].weight, features[2].weight)
    broken = tmp_path / "broken.pth"
    torch.save({"features.0.weight": features[0].weight}, broken)
    with pytest.raises(ValueError, match="not a VGG16 state dict"):
        VGGPerceptualLoss(str(broken), ("relu1_2",))


def test_perceptual_loss_is_zero_for_equal_images_and_has_gradient():
    loss = VGGPerceptualLoss("none", ("relu1_2", "relu2_2"))
    x = torch.rand(1, 3, 32, 32)
    assert loss(x, x).item() == 0.0
    y = torch.rand(1, 3, 32, 32, requires_grad=True)
    loss(y, x).backward()
    assert y.grad.abs().sum() > 0


def test_perceptual_missing_weights_say_where_to_put_them(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    with pytest.raises(FileNotFoundError, match="vgg16-397923af.pth"):
        resolve_weights("imagenet")
    with pytest.raises(FileNotFoundError, match="perceptual.weights"):
        VGGPerceptualLoss(str(tmp_path / "absent.pth"))
    with pytest.raises(ValueError, match="unknown VGG16 layers"):
        VGGPerceptualLoss("none", ("relu9_9",))


# ---- the eq. 1 weights reach the segmentation loss of both phases ----------------------------------------------
FRACTIONS = [0.4, 0.25, 0.15, 0.1, 0.05, 0.03, 0.015, 0.005]


def weighted_cross_entropy_by_hand(logits, labels, weights):
    """sum_p w[y_p] * -log softmax(logits_p)[y_p] / sum_p w[y_p], one pixel p at a time."""
    num, den = 0.0, 0.0
    log_prob = logits.double().log_softmax(dim=1)
    for b, y, x in itertools.product(*(range(n) for n in labels.shape)):
        c = int(labels[b, y, x])
        num += -float(weights[c]) * float(log_prob[b, c, y, x])
        den += float(weights[c])
    return num / den


def segmentation_batch():
    g = torch.Generator().manual_seed(0)
    return {"dynamic": torch.rand(2, 3, 32, 32, generator=g), "static": torch.rand(2, 3, 32, 32, generator=g),
            "label": torch.randint(0, 8, (2, 32, 32), generator=g), "mask": torch.zeros(2, 1, 32, 32)}


@pytest.mark.parametrize("formula", ["paper", "authors"])
def test_phase1_loss_is_the_eq1_weighted_cross_entropy(formula):
    torch.manual_seed(0)
    task = SegmentationTask(SegmentationConfig(model="fcn", segmenter_keys={"fcn": {"width": 4}},
                                               class_weight_formula=formula), 8,
                            FRACTIONS).eval()
    batch = segmentation_batch()
    loss = task.training_step(batch, None)["loss"]
    with torch.no_grad():
        logits = task.seg(batch["dynamic"])
    weights = [1 / math.log(r + 1.02) if formula == "paper" else 1 / math.log(100 * r + 1.02) for r in FRACTIONS]
    assert loss.item() == pytest.approx(weighted_cross_entropy_by_hand(logits, batch["label"], weights), rel=1e-5)
    unweighted = weighted_cross_entropy_by_hand(logits, batch["label"], [1.0] * 8)
    assert abs(loss.item() - unweighted) > 1e-3  # the weights change the loss on this batch


def test_phase2_segmentation_term_is_the_eq1_weighted_cross_entropy():
    torch.manual_seed(0)
    cfg = MMDIPConfig(segmentation=SegmentationConfig(model="fcn", segmenter_keys={"fcn": {"width": 4}}),
                      translation=TranslationConfig(num_downs=3, ngf=4, ndf=4, d_layers=2))
    task = JointTask(cfg, FRACTIONS, training=False).eval()
    task.configure_optimizers()
    batch = segmentation_batch()
    with torch.no_grad():
        logits = task.seg(batch["dynamic"])  # before the step: the term is computed from these
    engine = SimpleNamespace(autocast=contextlib.nullcontext, backward=lambda loss: loss.backward(),
                             step=lambda opt: (opt.step(), opt.zero_grad()))
    ce = task.training_step(batch, engine)["ce"]
    weights = [1 / math.log(r + 1.02) for r in FRACTIONS]
    assert ce.item() == pytest.approx(weighted_cross_entropy_by_hand(logits, batch["label"], weights), rel=1e-5)
