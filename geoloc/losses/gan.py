"""Least-squares GAN losses (Mao et al. 2017), as used for SSGGNet's adversarial term.

D minimises 1/2 E[(D(real) - 1)^2] + 1/2 E[D(fake)^2]; G minimises E[(D(fake) - 1)^2]. D outputs PatchGAN maps.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def lsgan_d_loss(real_logits: torch.Tensor, fake_logits: torch.Tensor) -> torch.Tensor:
    """Discriminator loss; `fake_logits` must come from detached generator outputs."""
    real = F.mse_loss(real_logits, torch.ones_like(real_logits))
    fake = F.mse_loss(fake_logits, torch.zeros_like(fake_logits))
    return 0.5 * (real + fake)


def lsgan_g_loss(fake_logits: torch.Tensor) -> torch.Tensor:
    """Generator loss: push D's output on fakes to the real label."""
    return F.mse_loss(fake_logits, torch.ones_like(fake_logits))
