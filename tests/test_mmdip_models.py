import pytest
import torch

from geoloc.models.erfnet import ERFNet
from geoloc.models.fcn import FCN8s
from geoloc.models.patchgan import PatchGAN
from geoloc.models.unet import UNet


def count(m):
    return sum(p.numel() for p in m.parameters())


def test_erfnet_has_about_2_06M_parameters_for_8_classes():
    assert 2.055e6 <= count(ERFNet(8)) <= 2.065e6


def test_erfnet_logits_shape_and_bad_size():
    m = ERFNet(8).eval()
    assert m(torch.rand(2, 3, 32, 48)).shape == (2, 8, 32, 48)
    with pytest.raises(ValueError, match="divisible by 8"):
        m(torch.rand(1, 3, 30, 32))


def test_unet_generator_is_pix2pix_sized_and_keeps_shape():
    assert count(UNet(3, 3, num_downs=8, ngf=64)) == pytest.approx(54.4e6, rel=0.01)
    g = UNet(16, 3, num_downs=4, ngf=8).eval()
    out = g(torch.rand(2, 16, 32, 32))
    assert out.shape == (2, 3, 32, 32) and out.abs().max() <= 1
    with pytest.raises(ValueError, match="divisible by 16"):
        g(torch.rand(1, 16, 24, 24))


def test_unet_skips_reach_the_output():
    g = UNet(1, 1, num_downs=3, ngf=4, final=None, dropout=False).eval()
    x = torch.zeros(1, 1, 16, 16, requires_grad=True)
    g(x)[0, 0, 0, 0].backward()
    assert x.grad.abs().sum() > 0


def test_patchgan_and_fcn_shapes():
    assert PatchGAN(6, ndf=8)(torch.rand(2, 6, 64, 64)).shape == (2, 1, 6, 6)
    assert FCN8s(8, width=8)(torch.rand(1, 3, 64, 32)).shape == (1, 8, 64, 32)
