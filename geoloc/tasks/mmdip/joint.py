"""Phase 2 of MMDIP: segmentation + semantics-guided generator (SSGGNet) + PatchGAN, trained end to end.

Losses: the registered generator loss `task.translation.generator_loss` names (generator_loss.py: LSGAN
adversarial, L1 and VGG16 perceptual on the recovered static image, weighted 1 / 1 / 1 as eq. 2 or 1 / 100 / 10 as
pix2pix), plus lambda_seg * the eq. 1 weighted cross-entropy that keeps the segmentation static. Per-module rates
(paper: 1e-4 segmentation, 2e-3 G, 4e-3 D): segmentation and G are two parameter groups of one Adam (one
backward, one step), D has its own. D and G alternate every batch, so the task steps its own optimizers
(`automatic_optimization = False`) through engine.backward / engine.step / engine.autocast.
The variants (ssggnet, ssggnet_sm, pix2pix, mgan) differ only in the generator input (networks.generator_input).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from geoloc.engine import Task
from geoloc.eval.image import image_scores_per_image
from geoloc.losses.gan import lsgan_d_loss
from geoloc.losses.segmentation import class_weights
from geoloc.tasks.mmdip.mmdip_config import MMDIPConfig
from geoloc.tasks.mmdip.generator_loss import build_generator_loss
from geoloc.tasks.mmdip.networks import (build_discriminator, build_generator, build_segmenter, generator_input,
                                         to_signed)
from geoloc.tasks.mmdip.segmentation import batch_confusion, confusion_metrics

LOSS_PREFIX = "generator_loss."


class JointTask(Task):
    monitor = "SSIM"
    automatic_optimization = False

    def __init__(self, cfg: MMDIPConfig, fractions, training: bool = True):
        super().__init__()
        self.cfg, self.tcfg, self.num_classes = cfg, cfg.translation, cfg.num_classes
        self.seg = build_segmenter(cfg.segmentation, cfg.num_classes)
        self.generator = build_generator(cfg.translation, cfg.num_classes)
        self.discriminator = build_discriminator(cfg.translation)
        self.register_buffer("class_weights", class_weights(fractions, cfg.segmentation.class_weight_formula))
        self.generator_loss = build_generator_loss(cfg.translation, training)

    def state_dict(self, *args, **kwargs):
        # the generator loss (a frozen VGG) is not learnable state: keep it out of checkpoints
        state = super().state_dict(*args, **kwargs)
        return type(state)((k, v) for k, v in state.items() if not k.startswith(LOSS_PREFIX))

    def load_state_dict(self, state_dict, strict: bool = True):
        own = {k: v for k, v in super().state_dict().items() if k.startswith(LOSS_PREFIX)}
        return super().load_state_dict({**state_dict, **own}, strict=strict)

    def configure_optimizers(self):
        betas = (self.tcfg.beta1, 0.999)
        gen = torch.optim.Adam([{"params": self.seg.parameters(), "lr": self.tcfg.lr_seg},
                                {"params": self.generator.parameters(), "lr": self.tcfg.lr_g}], betas=betas)
        disc = torch.optim.Adam(self.discriminator.parameters(), lr=self.tcfg.lr_d, betas=betas)
        self._optimizers = (gen, disc)  # manual optimization: training_step steps them itself
        return [gen, disc], []

    def translate(self, dynamic: torch.Tensor, mask: torch.Tensor | None = None):
        """dynamic B x 3 x H x W in [0, 1] -> (segmentation logits, recovered static image in [-1, 1])."""
        logits = self.seg(dynamic)
        return logits, self.recover(dynamic, logits, mask)

    def recover(self, dynamic: torch.Tensor, logits: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """The generator's half of translate: the recovered static image from the segmentation logits."""
        return self.generator(generator_input(self.tcfg.variant, dynamic, logits, mask))

    def training_step(self, batch, engine):
        gen_opt, disc_opt = self._optimizers
        dynamic, real = batch["dynamic"], to_signed(batch["static"])
        dyn_signed = to_signed(dynamic)
        with engine.autocast():
            logits, fake = self.translate(dynamic, batch.get("mask"))
            d_loss = lsgan_d_loss(self.discriminator(torch.cat([real, dyn_signed], 1)),
                                  self.discriminator(torch.cat([fake.detach(), dyn_signed], 1)))
        engine.backward(d_loss)
        engine.step(disc_opt)

        self.discriminator.requires_grad_(False)  # G's adversarial term must not leave gradients in D
        with engine.autocast():
            d_fake = self.discriminator(torch.cat([fake, dyn_signed], 1))
            ce = F.cross_entropy(logits.float(), batch["label"], weight=self.class_weights)
            terms = self.generator_loss(fake, d_fake, batch)
            loss = terms.pop("loss") + self.tcfg.lambda_seg * ce
        engine.backward(loss)
        engine.step(gen_opt)
        self.discriminator.requires_grad_(True)
        return {"loss": loss.detach(), "d_loss": d_loss.detach(), **{k: v.detach() for k, v in terms.items()},
                "ce": ce.detach()}

    def validation_step(self, batch):
        logits, fake = self.translate(batch["dynamic"], batch.get("mask"))
        scores = image_scores_per_image((fake.float().clamp(-1, 1) + 1) / 2, batch["static"].float())
        out = {k: v.float() for k, v in scores.items()}
        out["confusion"] = batch_confusion(logits.argmax(1), batch["label"], self.num_classes)
        out["index"] = batch["index"]
        return out

    def validation_epoch_end(self, outputs):
        metrics = {k: float(outputs[k].mean()) for k in ("L1", "L2", "PSNR", "SSIM")}
        seg = confusion_metrics(outputs["confusion"])
        metrics.update({"MIoU": seg["MIoU"], "PA": seg["PA"]})
        return metrics
