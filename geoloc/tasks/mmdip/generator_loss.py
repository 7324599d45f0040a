"""Phase 2's generator loss, a registered component (the `generator_loss` kind is declared here).

`task.translation.generator_loss` is its section: `name` picks the factory, `module` imports a plug-in's, and the
other keys are the factory's own, checked against its signature. A factory may also name the run-time arguments
`perceptual_weights`, `perceptual_layers` (task.translation's VGG16 settings) and `training` (False when a
checkpoint is only evaluated: no VGG is loaded then). It returns a module called once per generator step as

    loss(fake, d_fake, batch) -> {"loss": scalar, **terms to log}

fake: B×3×H×W recovered static image in [-1, 1]; d_fake: the discriminator's PatchGAN scores of fake ⊕ dynamic
(its parameters frozen for this step); batch: the training batch (`static` B×3×H×W in [0, 1], `dynamic`, `mask`,
`label`). The task adds lambda_seg × the weighted cross-entropy. A generator loss is a fixed criterion: nothing in
it is trained or checkpointed.

Built-ins, one weighted sum with two sets of defaults (LSGAN adversarial term, L1 to the static image, VGG16
perceptual distance):
  paper    MMDIP eq. 2, L_G = L_adv + L_pixel + L_perceptual: weights 1 / 1 / 1;
  pix2pix  pix2pix's lambda_L1 = 100 and pix2pixHD's VGG term 10: weights 1 / 100 / 10 (the CPU default).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from geoloc import registry
from geoloc.losses.gan import lsgan_g_loss
from geoloc.losses.perceptual import VGGPerceptualLoss
from geoloc.tasks.mmdip.mmdip_config import TranslationConfig
from geoloc.tasks.mmdip.networks import to_signed

RUNTIME = ("perceptual_weights", "perceptual_layers", "training")
registry.declare("generator_loss", section="task.translation.generator_loss", runtime=RUNTIME)


class WeightedGeneratorLoss(nn.Module):
    """adv · LSGAN(d_fake) + l1 · L1(fake, static) + perceptual · VGG16(fake, static); terms logged as g_adv, l1 and
    perceptual. The VGG16 is built only to train with a positive perceptual weight."""

    def __init__(self, adv: float, l1: float, perceptual: float, perceptual_weights: str,
                 perceptual_layers: list[str], training: bool):
        super().__init__()
        self.weights = {"adv": adv, "l1": l1, "perceptual": perceptual}
        self.perceptual = (VGGPerceptualLoss(perceptual_weights, tuple(perceptual_layers))
                           if training and perceptual > 0 else None)

    def forward(self, fake: torch.Tensor, d_fake: torch.Tensor, batch: dict) -> dict[str, torch.Tensor]:
        adv = lsgan_g_loss(d_fake)
        l1 = F.l1_loss(fake, to_signed(batch["static"]))
        loss = self.weights["adv"] * adv + self.weights["l1"] * l1
        perceptual = torch.zeros((), device=fake.device)
        if self.perceptual is not None:
            perceptual = self.perceptual((fake.float() + 1) / 2, batch["static"])
            loss = loss + self.weights["perceptual"] * perceptual
        return {"loss": loss, "g_adv": adv, "l1": l1, "perceptual": perceptual}


@registry.register("generator_loss", "paper")
def paper(perceptual_weights: str, perceptual_layers: list[str], training: bool, adv: float = 1.0, l1: float = 1.0,
          perceptual: float = 1.0) -> WeightedGeneratorLoss:
    return WeightedGeneratorLoss(adv, l1, perceptual, perceptual_weights, perceptual_layers, training)


@registry.register("generator_loss", "pix2pix")
def pix2pix(perceptual_weights: str, perceptual_layers: list[str], training: bool, adv: float = 1.0,
            l1: float = 100.0, perceptual: float = 10.0) -> WeightedGeneratorLoss:
    return WeightedGeneratorLoss(adv, l1, perceptual, perceptual_weights, perceptual_layers, training)


def build_generator_loss(cfg: TranslationConfig, training: bool) -> nn.Module:
    return registry.build("generator_loss", cfg.generator_loss, perceptual_weights=cfg.perceptual_weights,
                          perceptual_layers=list(cfg.perceptual_layers), training=training)
