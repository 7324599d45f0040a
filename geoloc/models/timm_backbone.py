"""Backbones from timm (ConvNeXt, ViT/DeiT, ...) through `features_only`, as multi-scale NCHW maps for any head.

timm is imported when a backbone is built, never when geoloc is imported (it takes seconds). ImageNet weights
are read offline only (geoloc.models.timm_weights); docs/backbones.md shows the keys.
"""

from __future__ import annotations

import difflib

import torch
from torch import nn

from geoloc.models.timm_weights import find_weights, read_checked_state_dict, size_mismatch_error
from geoloc.registry import register


class TimmBackbone(nn.Module):
    """A timm features_only network. Input B×3×H×W; output one B×C_k×h_k×w_k map per out index, fine to coarse.

    ViT-like models give their blocks' patch tokens as maps on the patch grid (prefix tokens dropped).
    `channels`, `reductions` (input stride of each map) and `out_indices` describe the maps; `mean` and `std`
    are the input normalisation the pretrained weights expect.
    """

    def __init__(self, body: nn.Module, model: str, out_indices: list[int]):
        super().__init__()
        self.body = body
        self.model_name = model
        self.out_indices = out_indices
        self.channels = list(body.feature_info.channels())
        self.reductions = list(body.feature_info.reduction())
        cfg = getattr(body, "pretrained_cfg", {}) or {}
        self.mean, self.std = tuple(cfg.get("mean", ())), tuple(cfg.get("std", ()))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        try:
            return list(self.body(x))
        except AssertionError as err:  # timm's patch embedding asserts the fixed input size of a ViT
            raise ValueError(f"timm backbone {self.model_name!r} cannot take a {tuple(x.shape)} input ({err}). A "
                             f"ViT is built for one input size: set backbone.model_args.img_size="
                             f"[{x.shape[-2]}, {x.shape[-1]}].") from err


@register("backbone", "timm")
def timm_backbone(model: str = "convnext_tiny", pretrained: bool = False, weights_path: str | None = None,
                  out_indices: list[int] | None = None, model_args: dict | None = None) -> TimmBackbone:
    """`timm.create_model(model, features_only=True, out_indices=..., **model_args)`, weights from local files only.

    out_indices index timm's feature levels (stages of a hierarchical model, blocks of a ViT); default
    `default_out_indices`. pretrained=true reads `weights_path`, else the hub caches; nothing is downloaded.
    """
    import timm

    model_args = dict(model_args or {})
    if weights_path and not pretrained:
        raise ValueError(f"backbone.weights_path={weights_path!r} is set but backbone.pretrained=false: set "
                         f"backbone.pretrained=true to load it, or drop weights_path.")
    skeleton = _skeleton(timm, model, model_args)
    levels = list(getattr(skeleton, "feature_info", None) or [])
    if not levels:
        raise ValueError(f"timm model {model!r} lists no feature levels (feature_info), so it has no features_only "
                         f"form; pick another backbone.model.")
    indices = _checked_out_indices(out_indices, [level["reduction"] for level in levels], model)
    kwargs = dict(features_only=True, out_indices=tuple(indices), **model_args)
    path = None
    if pretrained:
        cfg = timm.models.get_pretrained_cfg(model)
        path = find_weights(model, weights_path, cfg)
        state = read_checked_state_dict(path, model, skeleton, getattr(cfg, "classifier", None))
        # a state dict overlay is timm's highest-priority weight source, so its hub/URL paths are never reached;
        # num_classes=0 keeps timm's load strict (it relaxes it when the classifier size differs)
        kwargs.update(pretrained=True, pretrained_cfg_overlay=dict(state_dict=state, num_classes=0))
    try:
        body = timm.create_model(model, **kwargs)
    except RuntimeError as err:
        if path is not None and "size mismatch" in str(err):
            raise size_mismatch_error(err, path, model) from err
        raise
    return TimmBackbone(body, model, indices)


def default_out_indices(reductions: list[int]) -> list[int]:
    """The last three levels of a hierarchical model (ConvNeXt: strides 8, 16, 32, like VGG's conv3_3..conv5_3);
    for a ViT (one stride throughout), the ends of the three thirds of its depth: blocks 3, 7, 11 of 12, so the
    maps span early to late features, as the VGG taps do."""
    n = len(reductions)
    if len(set(reductions)) > 1:
        return list(range(max(0, n - 3), n))
    return sorted({max(0, k * n // 3 - 1) for k in (1, 2, 3)})


def _checked_out_indices(out_indices: list[int] | None, reductions: list[int], model: str) -> list[int]:
    if out_indices is None:
        return default_out_indices(reductions)
    n = len(reductions)
    bad = [i for i in out_indices if not -n <= int(i) < n]
    if bad or not out_indices:
        raise ValueError(f"backbone.out_indices={list(out_indices)} does not fit timm model {model!r}: it has {n} "
                         f"feature levels (0..{n - 1}, input strides {reductions}).")
    return sorted({int(i) % n for i in out_indices})


def _skeleton(timm, model: str, model_args: dict) -> nn.Module:
    """The full model, without weights (on the meta device: no memory, no init time), for its levels and keys."""
    if not timm.is_model(model):  # also refuses hf-hub: names, whose config timm would download
        close = difflib.get_close_matches(model, timm.list_models(), n=5)
        raise ValueError(f"backbone.model={model!r} is not a timm model; close names: {close} "
                         f"(timm.list_models('pattern*') lists them).")
    args = {**model_args, "num_classes": 0}
    try:
        with torch.device("meta"):
            return timm.create_model(model, **args)
    except TypeError as err:
        raise ValueError(f"backbone.model_args={model_args} do not fit timm model {model!r}: {err}") from None
    except (NotImplementedError, RuntimeError):  # a model whose init needs real tensor values
        return timm.create_model(model, **args)
