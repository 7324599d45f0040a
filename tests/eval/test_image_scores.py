import math

import numpy as np
import pytest
import torch
from geoloc.eval.image import image_scores


def reference_ssim(x, y):
    """Direct Wang et al. SSIM: every valid 11x11 window, Gaussian weights sigma 1.5, per channel, then mean."""
    r = np.arange(11) - 5
    g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * 1.5**2))
    g /= g.sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for ch in range(x.shape[2]):
        for i in range(x.shape[0] - 10):
            for j in range(x.shape[1] - 10):
                a, b = x[i : i + 11, j : j + 11, ch], y[i : i + 11, j : j + 11, ch]
                ma, mb = (g * a).sum(), (g * b).sum()
                va, vb = (g * (a - ma) ** 2).sum(), (g * (b - mb) ** 2).sum()
                cov = (g * (a - ma) * (b - mb)).sum()
                vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def pair(seed=0, shape=(19, 23, 3)):
    rng = np.random.default_rng(seed)
    x = rng.random(shape)
    y = np.clip(x + 0.1 * rng.standard_normal(shape), 0, 1)
    return x, y


def test_ssim_psnr_l1_l2_match_reference_formulas():
    x, y = pair()
    s = image_scores(x, y)
    mse = np.mean((x - y) ** 2)
    assert s["L1"] == pytest.approx(np.mean(np.abs(x - y)))
    assert s["L2"] == pytest.approx(mse)
    assert s["PSNR"] == pytest.approx(10 * math.log10(1 / mse))
    assert s["SSIM"] == pytest.approx(reference_ssim(x, y), abs=1e-10)


def test_ssim_matches_skimage():
    metrics = pytest.importorskip("skimage.metrics")
    x, y = pair(1, (40, 32, 3))
    want = metrics.structural_similarity(
        x, y, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=2
    )
    assert image_scores(x, y)["SSIM"] == pytest.approx(want, abs=1e-8)


def test_tensor_layouts_agree_and_identity():
    x, y = pair(2)
    chw = image_scores(torch.from_numpy(x).permute(2, 0, 1), torch.from_numpy(y).permute(2, 0, 1))
    assert chw == pytest.approx(image_scores(x, y))
    same = image_scores(x, x)
    assert same["SSIM"] == pytest.approx(1.0) and same["L1"] == 0.0


def test_batch_is_mean_of_images_and_bad_shapes():
    (x1, y1), (x2, y2) = pair(3), pair(4)
    b = lambda *a: torch.from_numpy(np.stack(a)).permute(0, 3, 1, 2)
    batch = image_scores(b(x1, x2), b(y1, y2))
    s1, s2 = image_scores(x1, y1), image_scores(x2, y2)
    for k in batch:
        assert batch[k] == pytest.approx((s1[k] + s2[k]) / 2)
    with pytest.raises(ValueError, match="differ"):
        image_scores(x1, y1[:-1])
    with pytest.raises(ValueError, match="at least 11x11"):
        image_scores(x1[:8, :8], y1[:8, :8])
