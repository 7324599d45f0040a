"""Image-recovery scores (MMDIP Table II): L1, L2 (mean squared error), PSNR (peak 1) and SSIM.

SSIM follows Wang et al. 2004: an 11 x 11 Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03, dynamic range 1,
population (not sample) statistics, computed per channel over the window positions that lie fully inside the
image ('valid'), then averaged. This equals scikit-image's structural_similarity(gaussian_weights=True,
sigma=1.5, use_sample_covariance=False, data_range=1).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def _gaussian_1d(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _to_bchw(x) -> torch.Tensor:
    """HxW, HxWxC (numpy, C <= 4), CxHxW or BxCxHxW (torch) -> float64 BxCxHxW."""
    is_tensor = isinstance(x, torch.Tensor)
    t = x.detach().cpu().double() if is_tensor else torch.from_numpy(np.asarray(x, dtype=np.float64))
    if t.ndim == 2:
        return t[None, None]
    if t.ndim == 3:
        channels_last = not is_tensor and t.shape[-1] <= 4
        return (t.permute(2, 0, 1) if channels_last else t)[None]
    if t.ndim == 4:
        return t
    raise ValueError(f"expected an image of 2-4 dims, got shape {tuple(t.shape)}")


def ssim_map_mean(pred: torch.Tensor, target: torch.Tensor, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Per-image mean SSIM of float64 BxCxHxW images in [0, 1]; returns a B tensor."""
    b, c, h, w = pred.shape
    if h < size or w < size:
        raise ValueError(f"SSIM needs images of at least {size}x{size}, got {h}x{w}")
    g = _gaussian_1d(size, sigma).to(pred)
    kh, kw = g.view(1, 1, size, 1).repeat(c, 1, 1, 1), g.view(1, 1, 1, size).repeat(c, 1, 1, 1)

    def blur(x):
        return F.conv2d(F.conv2d(x, kh, groups=c), kw, groups=c)

    c1, c2 = 0.01**2, 0.03**2
    mu_x, mu_y = blur(pred), blur(target)
    var_x = blur(pred * pred) - mu_x**2
    var_y = blur(target * target) - mu_y**2
    cov = blur(pred * target) - mu_x * mu_y
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return s.mean(dim=(1, 2, 3))


def image_scores_per_image(pred, target) -> dict[str, torch.Tensor]:
    """L1, L2, PSNR, SSIM of each image of a batch (B float64 tensors); same input layouts as image_scores."""
    p, t = _to_bchw(pred), _to_bchw(target)
    if p.shape != t.shape:
        raise ValueError(f"pred and target differ in shape: {tuple(p.shape)} vs {tuple(t.shape)}")
    diff = p - t
    mse = diff.pow(2).mean(dim=(1, 2, 3))
    return {
        "L1": diff.abs().mean(dim=(1, 2, 3)),
        "L2": mse,
        "PSNR": 10 * torch.log10(1.0 / mse.clamp_min(1e-20)),  # identical images: capped at 200 dB, not inf
        "SSIM": ssim_map_mean(p, t),
    }


def image_scores(pred, target) -> dict[str, float]:
    """L1, L2, PSNR, SSIM of images in [0, 1]; a batch (BxCxHxW) gives the mean of the per-image scores."""
    return {k: float(v.mean()) for k, v in image_scores_per_image(pred, target).items()}
