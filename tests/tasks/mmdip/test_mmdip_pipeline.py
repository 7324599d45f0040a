"""Tiny CPU runs of the MMDIP task: phase 1 -> phase 2 -> VPR evaluation, then evaluate() on the checkpoints."""

import dataclasses
import json

import cv2
import numpy as np
import pytest
import torch
from geoloc.config import ConfigError
from geoloc.tasks import mmdip
from geoloc.tasks.mmdip import retrieval
from geoloc.tasks.mmdip.mmdip_config import MMDIPConfig, TranslationConfig
from geoloc.models.fcn import FCN8s
from geoloc.tasks.mmdip.networks import build_generator, build_segmenter, generator_input
from geoloc.tasks.mmdip.pipeline import parse
from geoloc.tasks.mmdip.segmentation import SegmentationTask

from conftest import compose_evaluate, compose_train
from helpers.dynamic_data import TINY_MMDIP, evaluate, write_tiny_dynamic


@pytest.mark.parametrize("variant,channels", [("ssggnet", 16), ("ssggnet_sm", 16), ("pix2pix", 3), ("mgan", 4)])
def test_generator_input_channels_per_variant(variant, channels):
    dynamic, mask = torch.rand(2, 3, 16, 16), (torch.rand(2, 1, 16, 16) > 0.5).float()
    logits = torch.randn(2, 8, 16, 16)
    x = generator_input(variant, dynamic, logits, mask)
    assert x.shape == (2, channels, 16, 16)
    g = build_generator(TranslationConfig(variant=variant, num_downs=2, ngf=4), 8)
    assert g.downs[0][0].in_channels == channels
    if variant == "ssggnet":  # gray copied K times, then the softmax map S
        assert torch.allclose(x[:, 0], x[:, 7]) and torch.allclose(x[:, 8:], logits.softmax(1))
    if variant == "ssggnet_sm":
        assert torch.equal(x[:, 8:].argmax(1), logits.argmax(1)) and set(x[:, 8:].unique().tolist()) == {0.0, 1.0}


def test_config_errors_are_clear(tmp_path):
    with pytest.raises(ConfigError, match="variant"):
        mmdip.train(compose_train([*TINY_MMDIP, "task.translation.variant=cyclegan", f"run_dir={tmp_path}"]),
                    tmp_path)
    with pytest.raises(ConfigError, match="vocab_sz"):
        mmdip.train(compose_train([*TINY_MMDIP, "+task.vpr.vocab_sz=3", f"run_dir={tmp_path}"]), tmp_path)
    with pytest.raises(ConfigError, match=r"dataset.name='synthetic' is not a known mmdip_dataset; choose one of "
                                          r"\['carla4', 'dynamic', 'emptycities'"):
        mmdip.train(compose_train(["task=mmdip", "dataset=synthetic", f"run_dir={tmp_path}"]), tmp_path)
    assert compose_train(["task=mmdip", f"run_dir={tmp_path}"]).dataset.name == "dynamic"  # task=mmdip switches
    assert MMDIPConfig().translation.lr_d == 4e-3


@pytest.mark.parametrize("override,message", [
    ("+task.segmentation.unet_num_downs=3", r"task.segmentation.unet_num_downs is not a key of task.segmentation .*"
                                             r"task.segmentation.<segmenter>.<key>"),
    ("+task.segmentation.unett.num_downs=3", r"task.segmentation.unett is neither a key of task.segmentation nor a "
                                              r"registered segmenter \(\['erfnet', 'fcn', .*'unet'\]\)"),
    ("+task.segmentation.unet.num_down=3", r"task.segmentation.unet.num_down is not an argument of "
                                            r"geoloc.tasks.mmdip.networks.unet; its arguments are \['num_downs', 'ngf'\]"),
    ("+task.translation.generator_loss.l2=1", r"task.translation.generator_loss.l2 is not an argument of "
                                               r"geoloc.tasks.mmdip.generator_loss.pix2pix"),
    ("+dataset.presets=dynamic", r"dataset.presets is not an argument of geoloc.tasks.mmdip.readers.dynamic; its "
                                  r"arguments are \['preset', 'train_size'"),
    ("dataset.name=carla4", r"dataset.preset is not an argument of geoloc.tasks.mmdip.readers.carla4"),
])
def test_each_registered_part_checks_its_own_keys_at_start_up(override, message, tmp_path):
    """The segmenter, the generator loss and the reader each take only their own keys, named in the error."""
    with pytest.raises(ConfigError, match=message):
        parse(compose_train(["task=mmdip", override, f"run_dir={tmp_path}"]))


def test_each_segmenter_keeps_its_own_keys(tmp_path):
    """task.segmentation.<segmenter> sections sit side by side (Table I runs all three); the chosen one is built."""
    cfg = parse(compose_train(["task=mmdip", "+task.segmentation.fcn.width=8", "+task.segmentation.unet.ngf=4",
                               f"run_dir={tmp_path}"]))[0].segmentation
    assert cfg.model == "erfnet" and cfg.segmenter_keys == {"fcn": {"width": 8}, "unet": {"ngf": 4}}
    fcn = SegmentationTask(dataclasses.replace(cfg, model="fcn"), 8, [1 / 8] * 8).seg
    assert isinstance(fcn, FCN8s) and fcn.score5.in_channels == 16 * 8
    unet = SegmentationTask(dataclasses.replace(cfg, model="unet"), 8, [1 / 8] * 8).seg
    assert sum(p.numel() for p in unet.parameters()) < sum(p.numel() for p in build_segmenter(
        dataclasses.replace(cfg, model="unet", segmenter_keys={}), 8).parameters())


def eq5_ranks_by_hand(q_bow, q_spm, r_bow, r_spm, alpha, tol=1e-5):
    """Eq. 5 in float64, M = alpha cos(BoW) + (1 - alpha) cos(SPM) (a zero code has cosine 0), and for each
    query the number of other references strictly above its own: (ranks ignoring near-ties, ranks counting them)."""
    def cos(a, b):
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        return (a @ b.T) / np.maximum(np.outer(na, nb), 1e-300)

    m = alpha * cos(q_bow, r_bow) + (1 - alpha) * cos(q_spm, r_spm)
    own = np.diag(m)[:, None]
    others = ~np.eye(*m.shape, dtype=bool)
    return ((m > own + tol) & others).sum(1), ((m > own - tol) & others).sum(1)


@pytest.mark.slow
def test_tiny_phase1_phase2_vpr_then_evaluate(tmp_path, one_thread, monkeypatch):
    root = write_tiny_dynamic(tmp_path / "dyn", n_train=4, n_val=8)
    run = tmp_path / "run"
    cfg = compose_train([*TINY_MMDIP, f"dataset.root={root}", f"run_dir={run}"])
    fused_calls = []  # the codes the fused recall is computed from, and what it returned

    def spy_recall(q_bow, q_spm, r_bow, r_spm, alpha, ks):
        out = real_recall(q_bow, q_spm, r_bow, r_spm, alpha, ks)
        fused_calls.append(((q_bow, q_spm, r_bow, r_spm, alpha), out))
        return out

    real_recall = retrieval.recall
    monkeypatch.setattr(retrieval, "recall", spy_recall)
    result = mmdip.train(cfg, run)
    monkeypatch.setattr(retrieval, "recall", real_recall)
    for phase in ("phase1", "phase2"):
        assert (run / phase / "best.pt").is_file() and (run / phase / "last.pt").is_file()
    assert 0 <= result["phase1"]["MIoU"] <= 1 and 0 <= result["phase2"]["SSIM"] <= 1
    vpr = result
    assert vpr["num_queries"] == 8
    for key in ("R@1", "R@5", "R@10", "R@1%", "BoW/R@1", "SPM/R@1", "dynamic-BoW/R@1"):
        assert 0 <= vpr[key] <= 1
    # The fused recall is eq. 5 with alpha = 0.5, recomputed here in float64 (8 references: R@5 can miss)
    (q_bow, q_spm, r_bow, r_spm, alpha), (metrics, ranks) = fused_calls[0]
    assert alpha == 0.5 and q_bow.shape[0] == r_bow.shape[0] == 8
    low, high = eq5_ranks_by_hand(q_bow, q_spm, r_bow, r_spm, alpha)
    assert ((low <= ranks.numpy()) & (ranks.numpy() <= high)).all()
    for k in (1, 5, 10):
        assert vpr[f"R@{k}"] == metrics[f"R@{k}"] == float(np.mean(ranks.numpy() < k))
    assert vpr["R@1%"] == vpr["R@1"]  # K = max(1, floor(8 / 100)) = 1
    for artefact in ("vocabulary.npz", "gallery_val_predicted.npz"):
        assert (run / "vpr" / artefact).is_file()
    assert json.loads((run / "metrics.json").read_text())["R@1"] == vpr["R@1"]

    # evaluate() reuses the run's vocabulary and gallery, read only, and gives the same recall; it writes its
    # metrics to its own run dir, never into the training run
    records = {p.name: p.stat().st_mtime_ns for p in (run / "vpr").iterdir()}
    out = tmp_path / "metrics.json"
    again = evaluate(compose_train([*TINY_MMDIP, f"dataset.root={root}", f"run_dir={tmp_path / 'eval'}"]),
                     run / "phase2" / "best.pt", out)
    assert {k: again[k] for k in vpr if "R@" in k} == {k: vpr[k] for k in vpr if "R@" in k}
    assert json.loads(out.read_text())["num_queries"] == 8
    assert sorted(p.name for p in (tmp_path / "eval" / "vpr").iterdir()) == ["metrics_val.json"]
    # other weights: the gallery is coded again, into the evaluation's dir; the vocabulary (image settings only)
    # is the run's
    evaluate(compose_train([*TINY_MMDIP, f"dataset.root={root}", f"run_dir={tmp_path / 'eval_last'}"]),
             run / "phase2" / "last.pt")
    assert (tmp_path / "eval_last" / "vpr" / "gallery_val_predicted.npz").is_file()
    assert not (tmp_path / "eval_last" / "vpr" / "vocabulary.npz").exists()
    assert {p.name: p.stat().st_mtime_ns for p in (run / "vpr").iterdir()} == records

    # Empty Cities 3-panel images: static-image recovery scores, and the place protocol (tests/test_mmdip_realformat)
    ec = tmp_path / "ec"
    ec.mkdir()
    rng = np.random.default_rng(0)
    for i in range(2):
        cv2.imwrite(str(ec / f"{i}.png"), rng.integers(0, 255, (60, 240, 3), np.uint8))
    ec_cfg = compose_evaluate(["ckpt=x", "dataset=emptycities", f"dataset.root={ec}", "device=cpu"])
    scores = evaluate(ec_cfg, run / "phase2" / "best.pt", tmp_path / "ec.json")
    assert {"L1", "L2", "PSNR", "SSIM", "num_images"} <= set(scores) and scores["num_images"] == 2
    seg = evaluate(compose_train([*TINY_MMDIP, f"dataset.root={root}"]), run / "phase1" / "best.pt")
    assert {"PA", "MPA", "MIoU", "FWIoU"} <= set(seg)
