import pytest
import torch
import torch.nn.functional as F
from geoloc.models.erfnet import ERFNet, NonBottleneck1D, reference_state_dict
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


# ERFNet as released (Romera et al., erfnet_pytorch `Net`), written again with torch.nn.functional on a flat dict of
# reference-named tensors. Encoder: initial_block, then `layers`; decoder: `layers`, then output_conv. Each prefix
# below ends with "." (or is empty for a lone block).
REF_ENCODER = ([("down", 16, 64)] + [("block", 64, 1)] * 5 + [("down", 64, 128)]
               + [("block", 128, d) for d in (2, 4, 8, 16)] * 2)
REF_DECODER = [("up", 128, 64), ("block", 64, 1), ("block", 64, 1), ("up", 64, 16), ("block", 16, 1),
               ("block", 16, 1)]
BN_EPS = 1e-3  # erfnet_pytorch's BatchNorm2d(eps=1e-3)


def ref_bn(p, pre, x):
    return F.batch_norm(x, p[pre + "running_mean"], p[pre + "running_var"], p[pre + "weight"], p[pre + "bias"],
                        training=False, eps=BN_EPS)


def ref_conv(p, pre, x, padding, dilation=1):
    return F.conv2d(x, p[pre + "weight"], p[pre + "bias"], padding=padding, dilation=dilation)


def ref_block(p, pre, x, d):
    """non_bottleneck_1d: 3x1, ReLU, 1x3, BN, ReLU, dilated 3x1, ReLU, dilated 1x3, BN, + x, ReLU."""
    y = F.relu(ref_conv(p, pre + "conv3x1_1.", x, (1, 0)))
    y = F.relu(ref_bn(p, pre + "bn1.", ref_conv(p, pre + "conv1x3_1.", y, (0, 1))))
    y = F.relu(ref_conv(p, pre + "conv3x1_2.", y, (d, 0), (d, 1)))
    y = ref_bn(p, pre + "bn2.", ref_conv(p, pre + "conv1x3_2.", y, (0, d), (1, d)))
    return F.relu(y + x)


def ref_layer(p, pre, x, spec):
    kind, _, dilation = spec
    if kind == "block":
        return ref_block(p, pre, x, dilation)
    if kind == "down":
        conv = F.conv2d(x, p[pre + "conv.weight"], p[pre + "conv.bias"], stride=2, padding=1)
        return F.relu(ref_bn(p, pre + "bn.", torch.cat([conv, F.max_pool2d(x, 2, 2)], 1)))
    up = F.conv_transpose2d(x, p[pre + "conv.weight"], p[pre + "conv.bias"], stride=2, padding=1, output_padding=1)
    return F.relu(ref_bn(p, pre + "bn.", up))


def ref_erfnet(p, x):
    x = ref_layer(p, "encoder.initial_block.", x, ("down", 3, 16))
    for i, spec in enumerate(REF_ENCODER):
        x = ref_layer(p, f"encoder.layers.{i}.", x, spec)
    for i, spec in enumerate(REF_DECODER):
        x = ref_layer(p, f"decoder.layers.{i}.", x, spec)
    return F.conv_transpose2d(x, p["decoder.output_conv.weight"], p["decoder.output_conv.bias"], stride=2)


def random_bn(gen, pre, ch):
    """Trained-looking BN: means off zero, variances away from 1, scales of both signs, non-zero shifts."""
    return {pre + "weight": torch.empty(ch).uniform_(-1.5, 1.5, generator=gen),
            pre + "bias": torch.randn(ch, generator=gen) * 0.5,
            pre + "running_mean": torch.randn(ch, generator=gen) * 0.5,
            pre + "running_var": torch.empty(ch).uniform_(0.3, 2.0, generator=gen),
            pre + "num_batches_tracked": torch.tensor(1000)}


def random_conv(gen, pre, weight_shape, fan_in, out_channels):
    return {pre + "weight": torch.randn(*weight_shape, generator=gen) / fan_in ** 0.5,
            pre + "bias": torch.randn(out_channels, generator=gen) * 0.1}


def ref_layer_state(gen, pre, spec):
    kind, cin, cout = spec  # a block's third entry is its dilation: it keeps cin channels
    if kind == "block":
        p = {}
        for name, k in (("conv3x1_1", (3, 1)), ("conv1x3_1", (1, 3)), ("conv3x1_2", (3, 1)), ("conv1x3_2", (1, 3))):
            p.update(random_conv(gen, f"{pre}{name}.", (cin, cin, *k), 3 * cin, cin))
        return {**p, **random_bn(gen, pre + "bn1.", cin), **random_bn(gen, pre + "bn2.", cin)}
    if kind == "down":  # a 3x3 stride-2 conv to cout - cin channels, concatenated with the max-pooled input
        p = random_conv(gen, pre + "conv.", (cout - cin, cin, 3, 3), 9 * cin, cout - cin)
    else:  # ConvTranspose2d weights are in x out x k x k
        p = random_conv(gen, pre + "conv.", (cin, cout, 3, 3), 9 * cin / 4, cout)
    return {**p, **random_bn(gen, pre + "bn.", cout)}


def ref_erfnet_state(num_classes, seed=0):
    """A reference-named state dict as saved from DataParallel, with the encoder-only output_conv it carries."""
    gen = torch.Generator().manual_seed(seed)
    p = ref_layer_state(gen, "encoder.initial_block.", ("down", 3, 16))
    for i, spec in enumerate(REF_ENCODER):
        p.update(ref_layer_state(gen, f"encoder.layers.{i}.", spec))
    for i, spec in enumerate(REF_DECODER):
        p.update(ref_layer_state(gen, f"decoder.layers.{i}.", spec))
    p.update(random_conv(gen, "encoder.output_conv.", (num_classes, 128, 1, 1), 128, num_classes))
    p.update(random_conv(gen, "decoder.output_conv.", (16, num_classes, 2, 2), 16, num_classes))
    return {"module." + k: v for k, v in p.items()}


def test_erfnet_block_matches_the_reference_order_with_trained_bn():
    gen = torch.Generator().manual_seed(1)
    state = ref_layer_state(gen, "", ("block", 8, 2))
    block = NonBottleneck1D(8, dropout=0.3, dilation=2)
    block.load_state_dict(state)
    x = torch.randn(2, 8, 12, 10, generator=gen)
    assert torch.allclose(block.eval()(x), ref_block(state, "", x, 2), atol=1e-5, rtol=1e-5)


def test_erfnet_loads_reference_weights_and_computes_the_reference_function():
    state = ref_erfnet_state(num_classes=5)
    model = ERFNet(5)
    model.load_state_dict(reference_state_dict(state))  # strict: every key maps, none is left over
    x = torch.rand(2, 3, 32, 24, generator=torch.Generator().manual_seed(2))
    expected = ref_erfnet({k.removeprefix("module."): v for k, v in state.items()}, x)
    assert expected.std() > 0.1  # the weights keep the signal alive through all 23 blocks
    assert torch.allclose(model.eval()(x), expected, atol=1e-4 * expected.abs().max().item(), rtol=1e-4)


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
