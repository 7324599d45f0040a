"""VGG16 trunk with taps at conv3_3, conv4_3 and conv5_3, and offline-only ImageNet weight loading."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn
from geoloc.models import packaged_weights

# The files torchvision's VGG16_Weights.IMAGENET1K_V1 / VGG16_BN_Weights.IMAGENET1K_V1 download into the hub cache.
IMAGENET_FILE = "vgg16-397923af.pth"
IMAGENET_BN_FILE = "vgg16_bn-6c64b313.pth"
_TAP_CONVS = (7, 10, 13)  # conv3_3, conv4_3, conv5_3 are the 7th, 10th and 13th convolutions
# VGG16 ("configuration D"): output channels of each 3x3 convolution, "M" a 2x2 max pool
VGG16_LAYERS = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")


class MissingWeightsError(FileNotFoundError):
    pass


def weights_file(weights_path: str, contents: str, backbone: str = "vgg16") -> Path:
    """`backbone.weights_path` as an existing file (`geoloc:NAME`: the checked file shipped with geoloc for a
    `backbone` trunk); MissingWeightsError saying what it should hold otherwise."""
    if packaged_weights.is_packaged(weights_path):
        return packaged_weights.packaged_file(weights_path, backbone)
    path = Path(weights_path).expanduser()
    if not path.is_file():
        raise MissingWeightsError(f"backbone.weights_path={weights_path!r} does not exist. Point it at {contents}.")
    return path


def imagenet_weights_path(weights_path: str | None = None, filename: str = IMAGENET_FILE) -> Path:
    """Where VGG16 ImageNet weights are read from: an explicit file, else torchvision's hub cache.

    Nothing is downloaded: these machines are often offline, and a silent download would change results.
    """
    if weights_path:
        return weights_file(weights_path, f"a VGG16 ImageNet state dict such as torchvision's {filename}")
    path = Path(torch.hub.get_dir()) / "checkpoints" / filename
    if not path.is_file():
        raise MissingWeightsError(
            f"ImageNet VGG16 weights not found offline at {path}. Download {filename} (torchvision's "
            f"ImageNet VGG16 weights) on a connected machine and copy it there, or set "
            f"backbone.weights_path=/path/to/{filename}; or train from scratch with backbone.pretrained=false.")
    return path


def load_imagenet_features(features: nn.Sequential, weights_path: str | None = None,
                           filename: str = IMAGENET_FILE) -> None:
    """Copy the conv weights of a torchvision VGG16 state dict into `features` (the classifier is unused). A file
    that cannot be read, holds another network, or holds only part of VGG16 (a copy cut short, a trunk saved
    without its last blocks) is refused naming the file and what is wrong, before any weight is copied."""
    path = imagenet_weights_path(weights_path, filename)
    refetch = (f"Fetch torchvision's {filename} again on a connected machine and point backbone.weights_path at it, "
               "or train from scratch with backbone.pretrained=false.")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated or not a tensor file: torch's own message runs to a page
        first = next((line for line in str(err).splitlines() if line.strip()), "")
        raise ValueError(f"cannot read {path} as a state dict ({type(err).__name__}: {first}). {refetch}") from err
    if not isinstance(state, dict):
        raise ValueError(f"{path} holds a {type(state).__name__}, not a state dict. {refetch}")
    conv = {k[len("features."):]: v for k, v in state.items() if k.startswith("features.")}
    if not conv:
        raise ValueError(f"{path} holds no 'features.*' keys; it is not a torchvision VGG16 state dict. {refetch}")
    own = features.state_dict()
    missing = [f"features.{k}" for k in own if k not in conv]
    shapes = [f"features.{k}: file {tuple(conv[k].shape)} vs VGG16 {tuple(v.shape)}"
              for k, v in own.items() if k in conv and conv[k].shape != v.shape]
    if missing or shapes:
        found = f"{len(own) - len(missing)} of the {len(own)} tensors of the VGG16 trunk"
        raise ValueError(f"{path} holds {found}: it is partial or another network "
                         f"({'missing ' + ', '.join(missing[:3]) if missing else ''}"
                         f"{'; ' if missing and shapes else ''}{'mis-shaped ' + '; '.join(shapes[:2]) if shapes else ''}"
                         f"). {refetch}")
    features.load_state_dict({k: conv[k] for k in own})


def check_packaged(weights_path: str | None, width: float, batchnorm: bool) -> None:
    """Weights shipped with geoloc fit one trunk: refuse them for another width or batchnorm, saying which fits."""
    if not packaged_weights.is_packaged(weights_path):
        return
    fits = packaged_weights.card(weights_path)["backbone"]
    if (fits.get("width"), fits.get("batchnorm")) != (width, batchnorm):
        raise ValueError(f"backbone.weights_path={weights_path!r} is a VGG16 trunk at width {fits.get('width')} "
                         f"with batchnorm={fits.get('batchnorm')}; this backbone has width {width} and batchnorm="
                         f"{batchnorm}: set backbone.width={fits.get('width')} "
                         f"backbone.batchnorm={str(fits.get('batchnorm')).lower()}.")


def vgg16_layers(batchnorm: bool, inplace: bool = True) -> list[nn.Module]:
    """VGG16's layers in torchvision's order and indices (3x3 convolutions, [batch norm,] ReLU; 2x2 max pools),
    each with PyTorch's own initial weights."""
    layers, in_channels = [], 3
    for v in VGG16_LAYERS:
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            continue
        conv = nn.Conv2d(in_channels, v, kernel_size=3, padding=1)
        layers += [conv, nn.BatchNorm2d(v), nn.ReLU(inplace)] if batchnorm else [conv, nn.ReLU(inplace)]
        in_channels = v
    return layers


def vgg16_features_as_torchvision(batchnorm: bool) -> nn.Sequential:
    """VGG16's convolutional layers (torchvision's `vgg16(_bn)().features`, the same modules at the same indices),
    initialised with the same draws from the global generator in the same order as torchvision's constructor makes
    them: each layer's own init as it is built, the three classifier layers' too, then VGG's init (He-normal
    convolutions, unit batch norms, N(0, 0.01) linear layers). The classifier is dropped, but its draws are kept:
    the generator's state after them decides every weight drawn next, so a seed gives the weights it gave when the
    trunk was cut from torchvision's whole VGG16 (tests/models/test_vgg_draws.py builds both). Building it here
    spares every process torchvision's import (about 3 s: it imports torch._dynamo)."""
    features = nn.Sequential(*vgg16_layers(batchnorm))
    classifier = [nn.Linear(512 * 7 * 7, 4096), nn.Linear(4096, 4096), nn.Linear(4096, 1000)]
    for module in [*features, *classifier]:
        if isinstance(module, nn.Conv2d):
            nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
            nn.init.constant_(module.bias, 0)
        elif isinstance(module, nn.BatchNorm2d):
            nn.init.constant_(module.weight, 1)
            nn.init.constant_(module.bias, 0)
        elif isinstance(module, nn.Linear):
            nn.init.normal_(module.weight, 0, 0.01)
            nn.init.constant_(module.bias, 0)
    return features


class VGG16Trunk(nn.Module):
    """VGG16 conv layers up to conv5_3 (no pool5), returning the three tapped maps.

    `width` scales every layer's channels (1.0 is the real VGG16; smaller widths train on a CPU).
    `batchnorm` uses VGG16-BN, which trains from scratch far more readily than plain VGG16.
    Input B×3×H×W; outputs conv3_3 (B×256w×H/4×W/4), conv4_3 (B×512w×H/8×W/8), conv5_3 (B×512w×H/16×W/16).
    """

    def __init__(self, width: float = 1.0, pretrained: bool = False, weights_path: str | None = None,
                 batchnorm: bool = False):
        super().__init__()
        full = vgg16_features_as_torchvision(batchnorm)
        taps, convs = [], 0
        for i, layer in enumerate(full):
            convs += isinstance(layer, nn.Conv2d)
            if isinstance(layer, nn.ReLU) and convs in _TAP_CONVS and convs not in [c for c, _ in taps]:
                taps.append((convs, i))
        features = full[: taps[-1][1] + 1]  # up to conv5_3's ReLU: no pool5
        if width != 1.0:
            features = _scaled(features, width)
        if pretrained:
            check_packaged(weights_path, width, batchnorm)
            if width != 1.0 and not weights_path:
                raise ValueError("backbone.pretrained=true needs backbone.width=1.0 (ImageNet weights are full width), "
                                 "or backbone.weights_path at a trunk of this width (geoloc:synthetic_vgg16_cpu for "
                                 "width 0.125 with batchnorm).")
            load_imagenet_features(features, weights_path, IMAGENET_BN_FILE if batchnorm else IMAGENET_FILE)
        self.features = features
        self.taps = [i for _, i in taps]
        conv_layers = [m for m in features if isinstance(m, nn.Conv2d)]
        self.channels = [conv_layers[c - 1].out_channels for c in _TAP_CONVS]

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        taps = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                taps.append(x)
        return taps


def _scaled(features: nn.Sequential, width: float) -> nn.Sequential:
    layers, in_ch = [], 3
    for layer in features:
        if isinstance(layer, nn.Conv2d):
            out_ch = max(4, round(layer.out_channels * width))
            layers.append(nn.Conv2d(in_ch, out_ch, kernel_size=3, padding=1))
            in_ch = out_ch
        elif isinstance(layer, nn.BatchNorm2d):
            layers.append(nn.BatchNorm2d(in_ch))
        else:
            layers.append(layer)
    return nn.Sequential(*layers)
