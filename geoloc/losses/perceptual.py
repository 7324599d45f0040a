"""VGG16 perceptual loss (Johnson et al. 2016) for SSGGNet: L1 between frozen VGG16 feature maps.

Weights (`weights`):
  "imagenet"  torchvision's ImageNet checkpoint, read from the torch hub cache only (never downloaded here);
  a path      a local state dict: a full torchvision vgg16 one ("features.N.weight" keys) or a features-only one;
  "none"      random, frozen features (seeded): for tests and CPU smoke runs; documented as not the paper's loss.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from geoloc.models.vgg import MissingWeightsError, imagenet_weights_path, vgg16_layers

LAYERS = {"relu1_2": 3, "relu2_2": 8, "relu3_3": 15, "relu4_3": 22}
_MEAN, _STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)


def _load_features_state(path: Path) -> dict[str, torch.Tensor]:
    state = torch.load(path, map_location="cpu", weights_only=True)
    if any(k.startswith("features.") for k in state):
        state = {k[len("features.") :]: v for k, v in state.items() if k.startswith("features.")}
    return state


def resolve_weights(weights: str) -> Path | None:
    """Map the `weights` option to a file (None for random weights); fail with where to put the file."""
    if weights in ("none", "", None):
        return None
    try:  # the same offline lookup as the cross-view VGG16 trunk (hub cache or a local file)
        return imagenet_weights_path(None if weights == "imagenet" else weights)
    except MissingWeightsError as err:
        raise MissingWeightsError(f"{err} For the perceptual loss: perceptual.weights=/path/to/vgg16.pth, or "
                                  "perceptual.weights=none for random features.") from None


def vgg16_features(n_layers: int) -> nn.Sequential:
    """The first `n_layers` modules of torchvision's vgg16().features, same indices (so state dicts load),
    built without the 120M-parameter classifier."""
    return nn.Sequential(*vgg16_layers(batchnorm=False, inplace=False)[:n_layers])


class VGGPerceptualLoss(nn.Module):
    """Mean over `layers` of L1(VGG16(pred), VGG16(target)); inputs B x 3 x H x W in [0, 1]."""

    def __init__(self, weights: str = "none", layers: tuple[str, ...] = ("relu1_2", "relu2_2", "relu3_3")):
        super().__init__()
        unknown = set(layers) - set(LAYERS)
        if unknown or not layers:
            raise ValueError(f"unknown VGG16 layers {sorted(unknown)}; choose from {list(LAYERS)}")
        self.taps = sorted(LAYERS[name] for name in layers)
        path = resolve_weights(weights)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)  # random features are the same in every run
            features = vgg16_features(self.taps[-1] + 1)
        if path is not None:
            state = _load_features_state(path)
            missing, _ = features.load_state_dict(state, strict=False)
            if missing:
                raise ValueError(f"{path} is not a VGG16 state dict: missing {missing[:4]}")
        self.features = features.requires_grad_(False).eval()
        self.register_buffer("mean", torch.tensor(_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_STD).view(1, 3, 1, 1), persistent=False)

    def train(self, mode: bool = True):
        super().train(mode)
        self.features.eval()  # frozen feature extractor
        return self

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        x = (x - self.mean) / self.std
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
        return out

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            target_feats = self._taps(target)
        return sum(F.l1_loss(p, t) for p, t in zip(self._taps(pred), target_feats)) / len(self.taps)
