"""Each paper experiment holds the paper's numbers, passes the runners' schemas, and reaches the code that uses it.

MSAE (Li et al.): Adam 1e-4, betas 0.9/0.999, StepLR /10 at epoch 80, 100 epochs, batch 64, IPT at 288x288, alpha 10,
eq. 3 with no activation, random rotation of the IPT query and no colour jitter. geoloc's choices where the paper is
silent: the +-10 degree range, and the GMS queue's length (1024).
MMDIP (Wu, Wang, Sun): ERFNet Adam 2e-3 batch 1; SSGGNet lrs 1e-4 segmentation / 2e-3 G / 4e-3 D, batch 4; eq. 2's
unit generator loss weights; VGG16 ImageNet perceptual loss; SPM L = 2; alpha 0.5; 512x512 everywhere.
"""

from __future__ import annotations

import contextlib

import pytest
import torch
from geoloc import registry
from geoloc.config import ConfigError, checked
from geoloc.engine import TrainerConfig
from geoloc.models.crossview import CrossViewModelConfig
from geoloc.synthetic.world_config import resolve
from geoloc.tasks.crossview.data_config import parse_dataset
from geoloc.tasks.mmdip.joint import JointTask
from geoloc.tasks.mmdip.pipeline import parse
from geoloc.tasks.mmdip.segmentation import SegmentationTask
from omegaconf import OmegaConf

from conftest import compose_train, write_cvusa
from helpers.crossview_runs import pairs_of

CROSSVIEW = {"paper_cvusa": "cvusa", "paper_cvact": "cvact"}
FRACTIONS = [0.05, 0.3, 0.05, 0.1, 0.02, 0.3, 0.1, 0.08]


def crossview_sections(experiment: str, root, overrides=()) -> dict:
    """The experiment's groups as the cross-view runner reads them (unknown keys and bad values fail)."""
    cfg = compose_train([f"experiment={experiment}", f"dataset.root={root}", f"run_dir={root}", *overrides])
    plain = lambda section: OmegaConf.create(OmegaConf.to_container(section, resolve=True))  # noqa: E731
    registry.check("loss", cfg.loss)
    registry.check("optimizer", cfg.optim)
    return {"dataset": parse_dataset(cfg.dataset)[0], "model": checked(cfg.model, CrossViewModelConfig, "model"),
            "backbone": plain(cfg.backbone), "head": plain(cfg.head), "loss": plain(cfg.loss),
            "optim": plain(cfg.optim), "sampler": plain(cfg.sampler),
            "trainer": checked(cfg.trainer, TrainerConfig, "trainer")}


@pytest.mark.parametrize("experiment", sorted(CROSSVIEW))
def test_crossview_paper_config_holds_the_msae_numbers(experiment, tmp_path):
    c = crossview_sections(experiment, tmp_path)
    d, m, loss, opt = c["dataset"], c["model"], c["loss"], c["optim"]
    assert d.name == CROSSVIEW[experiment]
    assert (d.alignment, d.aerial_size, d.batch_size) == ("ipt", 288, 64)  # IPT query and aerial both 288x288
    assert d.rotation_deg == 10.0 and d.color_jitter == 0.0 and not d.joint_flip_rotate
    b, h = c["backbone"], c["head"]
    assert (b.name, b.width, b.pretrained, b.batchnorm) == ("vgg16", 1.0, True, False)
    assert (h.name, h.scale_channels, h.proj_channels, h.pool) == ("msae", 64, 64, 8)
    assert h.scale_activation == "none"  # eq. 3 as written
    assert (m.dim, m.shared) == (4096, False) and c["sampler"].name == "shuffle"
    assert (loss.name, loss.alpha, loss.queue_start_epoch) == ("gms_triplet", 10.0, 0)
    assert loss.queue_size == 1024  # geoloc's choice: the paper gives no length
    assert (opt.name, opt.lr, tuple(opt.betas), opt.weight_decay) == ("adam", 1e-4, (0.9, 0.999), 0.0)
    assert (opt.step_size, opt.gamma) == (80, 0.1)
    assert c["trainer"].max_epochs == 100


@pytest.mark.parametrize("experiment", sorted(CROSSVIEW))
def test_crossview_paper_schedule_divides_lr_by_10_at_epoch_80(experiment, tmp_path):
    c = crossview_sections(experiment, tmp_path)
    from conftest import tiny_task

    (opt,), (sched,) = tiny_task(loss=dict(c["loss"]), optim=dict(c["optim"])).configure_optimizers()
    assert opt.param_groups[0]["betas"] == (0.9, 0.999)
    lrs = []
    for _ in range(c["trainer"].max_epochs):  # the trainer steps the scheduler once per epoch
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[0] == lrs[79] == pytest.approx(1e-4)
    assert lrs[80] == lrs[99] == pytest.approx(1e-5)


def test_paper_cvusa_augmentation_rotates_the_query_only(tmp_path):
    root = write_cvusa(tmp_path / "cvusa", n_train=2, n_val=1)
    cfg = crossview_sections("paper_cvusa", root)["dataset"]
    pairs = pairs_of(cfg, "train", train=True, augment_seed=0)
    first, later = pairs[(0, 0)], pairs[(0, 1)]  # one place in two epochs: two draws of the augmentation
    assert first["query"].shape == first["reference"].shape == (3, 288, 288)
    assert not torch.equal(first["query"], later["query"])  # rotation on
    assert torch.equal(first["reference"], later["reference"])  # no colour jitter, no joint flip


def mmdip_sections(overrides=()):
    cfg = compose_train(["experiment=paper_mmdip", *overrides])
    return parse(cfg)  # the MMDIP runner's own schema check: task, dataset, trainer


def test_mmdip_paper_config_holds_the_paper_numbers():
    task, dataset, _ = mmdip_sections()
    seg, tr, vpr = task.segmentation, task.translation, task.vpr
    assert (seg.model, seg.lr, seg.batch_size, seg.class_weight_formula) == ("erfnet", 2e-3, 1, "paper")
    assert (tr.variant, tr.lr_seg, tr.lr_g, tr.lr_d, tr.batch_size) == ("ssggnet", 1e-4, 2e-3, 4e-3, 4)
    assert tr.generator_loss == {"name": "paper"}  # eq. 2's unit weights: test_mmdip_generator_loss_...
    assert tr.perceptual_weights == "imagenet"
    assert (tr.num_downs, tr.ngf, tr.ndf, tr.d_layers) == (8, 64, 64, 3)  # pix2pix U-Net, 70x70 PatchGAN
    assert (vpr.levels, vpr.alpha) == (2, 0.5)
    assert (seg.epochs, tr.epochs) == (100, 100)  # geoloc's choice, stated in the yaml


def test_mmdip_paper_config_renders_and_trains_at_512():
    task, dataset, _ = mmdip_sections()
    synthetic = dataset.reader_keys  # the `dynamic` reader's own keys
    assert dataset.image_size == [512, 512] and synthetic["view_size"] == 512
    rendered, _ = resolve("dynamic", synthetic["preset"], {"view_size": synthetic["view_size"]})
    assert rendered.view_size == 512  # what the generator draws is what the networks see: nothing upsampled
    assert all(side % 2 ** task.translation.num_downs == 0 for side in dataset.image_size)  # the U-Net takes it


class StubEngine:
    """What JointTask.training_step asks of the trainer, on the CPU in fp32."""

    def autocast(self):
        return contextlib.nullcontext()

    def backward(self, loss):
        loss.backward()

    def step(self, optimizer):
        optimizer.step()
        optimizer.zero_grad()


GENERATOR_LOSS_WEIGHTS = {"paper": {"adv": 1.0, "l1": 1.0, "perceptual": 1.0},  # eq. 2
                          "pix2pix": {"adv": 1.0, "l1": 100.0, "perceptual": 10.0}}  # lambda_L1 100, VGG 10


@pytest.mark.parametrize("weights", ["paper", "pix2pix"])
def test_mmdip_generator_loss_uses_the_named_weights(weights):
    small = ["task.translation.num_downs=3", "task.translation.ngf=4", "task.translation.ndf=4",
             "task.translation.d_layers=1", "task.translation.perceptual_weights=none",
             "task.translation.perceptual_layers=[relu1_2]", f"task.translation.generator_loss.name={weights}"]
    task_cfg, _, _ = mmdip_sections(small)
    torch.manual_seed(0)
    task = JointTask(task_cfg, FRACTIONS)
    gen_opt, disc_opt = task.configure_optimizers()[0]
    assert [g["lr"] for g in gen_opt.param_groups] == [1e-4, 2e-3] and disc_opt.param_groups[0]["lr"] == 4e-3
    assert gen_opt.param_groups[0]["betas"] == (0.5, 0.999)
    batch = {"dynamic": torch.rand(2, 3, 16, 16), "static": torch.rand(2, 3, 16, 16),
             "label": torch.randint(0, 8, (2, 16, 16)), "index": torch.arange(2)}
    out = task.training_step(batch, StubEngine())
    w = GENERATOR_LOSS_WEIGHTS[weights]
    expected = w["adv"] * out["g_adv"] + w["l1"] * out["l1"] + w["perceptual"] * out["perceptual"] + out["ce"]
    assert min(out["g_adv"], out["l1"], out["perceptual"]) > 0  # every term present, so a swapped weight shows
    assert out["loss"] == pytest.approx(float(expected), rel=1e-5)
    assert task.generator_loss.weights == w


def test_mmdip_phase1_optimizer_follows_the_paper_config():
    task_cfg, _, _ = mmdip_sections()
    (opt,), _ = SegmentationTask(task_cfg.segmentation, task_cfg.num_classes, FRACTIONS).configure_optimizers()
    assert opt.param_groups[0]["lr"] == 2e-3


@pytest.mark.parametrize("experiment,typo,named", [
    ("paper_cvusa", "+dataset.rotation_degs=10", "rotation_degs"),
    ("paper_cvact", "+optim.step=80", "step"),
    ("paper_mmdip", "+task.translation.loss_weight=paper", "loss_weight"),
    ("paper_mmdip", "task.translation.generator_loss.name=unit", r"generator_loss.name='unit' is not a known"),
    ("paper_mmdip", "+task.translation.generator_loss.l_1=1", r"generator_loss.l_1 is not an argument"),
])
def test_a_typo_in_a_paper_config_fails_at_start_up(experiment, typo, named, tmp_path):
    with pytest.raises(ConfigError, match=named):
        if experiment == "paper_mmdip":
            mmdip_sections([typo])
        else:
            crossview_sections(experiment, tmp_path, [typo])
