"""A generator-loss plug-in for task=mmdip: the hinge GAN generator term (Lim & Ye 2017) plus a weighted L1."""

import torch
import torch.nn.functional as F
from geoloc.registry import register
from torch import nn


class L1Hinge(nn.Module):
    def __init__(self, l1: float):
        super().__init__()
        self.l1 = l1

    def forward(self, fake: torch.Tensor, d_fake: torch.Tensor, batch: dict) -> dict:
        adv = -d_fake.mean()
        l1 = F.l1_loss(fake, batch["static"] * 2 - 1)
        return {"loss": adv + self.l1 * l1, "g_adv": adv, "l1": l1}


@register("generator_loss", "l1_hinge")
def l1_hinge(l1: float = 10.0) -> L1Hinge:
    return L1Hinge(l1)
