"""Offline-only ImageNet weights for timm backbones: find the file, read it, check it fits the model.

Nothing here touches the network. A file is read from `backbone.weights_path`, else from the Hugging Face hub
cache (where `timm.create_model(..., pretrained=True)` would have downloaded it) or the torch hub cache (timm's
older URL weights). The state dict is then handed to timm, which applies the model's own checkpoint filter (e.g.
resampling a ViT's position embeddings to another img_size) and loads it into the full model before the
features_only wrapper is put on.
"""

from __future__ import annotations

import os
from pathlib import Path
from urllib.parse import urlparse

import torch

from geoloc.models.vgg import MissingWeightsError, weights_file

# what timm.models.load_state_dict_from_hf reads from a timm/<model> hub repo, in its order of preference
HF_FILENAMES = ("model.safetensors", "pytorch_model.bin")


def hf_hub_cache() -> Path:
    """The Hugging Face hub cache dir, read from the environment now (huggingface_hub fixes it at import)."""
    for var in ("HF_HUB_CACHE", "HUGGINGFACE_HUB_CACHE"):
        if os.environ.get(var):
            return Path(os.environ[var]).expanduser()
    if os.environ.get("HF_HOME"):
        return Path(os.environ["HF_HOME"]).expanduser() / "hub"
    from huggingface_hub import constants

    return Path(constants.HF_HUB_CACHE)


def find_weights(model: str, weights_path: str | None, pretrained_cfg) -> Path:
    """The local file of `model`'s ImageNet weights; MissingWeightsError saying where it looked when none is."""
    if weights_path:
        return weights_file(weights_path, f"the state dict of the full timm model {model!r} (.safetensors, .pth or "
                                          ".bin)", backbone="timm")
    from huggingface_hub import try_to_load_from_cache  # reads the cache folder only, never the network

    hub_id = getattr(pretrained_cfg, "hf_hub_id", None)
    url = getattr(pretrained_cfg, "url", None)
    if not hub_id and not url:
        raise MissingWeightsError(f"timm has no pretrained weights registered for {model!r}: set "
                                  f"backbone.weights_path=/path/to/weights, or backbone.pretrained=false.")
    looked = []
    if hub_id:
        cache = hf_hub_cache()
        names = [pretrained_cfg.hf_hub_filename] if pretrained_cfg.hf_hub_filename else HF_FILENAMES
        for name in names:
            found = try_to_load_from_cache(hub_id, name, cache_dir=cache)
            if isinstance(found, str):
                return Path(found)
        looked.append(f"the Hugging Face hub cache {cache} (repo {hub_id}, file {' or '.join(names)})")
    if url:
        path = Path(torch.hub.get_dir()) / "checkpoints" / Path(urlparse(url).path).name
        if path.is_file():
            return path
        looked.append(str(path))
    fetch = (f"`hf download {hub_id} {HF_FILENAMES[0]}` (huggingface_hub's CLI), then copy the file to this machine"
             if hub_id else f"{url}, then copy it to this machine")
    raise MissingWeightsError(
        f"ImageNet weights of timm model {model!r} not found offline; looked in {'; '.join(looked)}. Nothing is "
        f"downloaded. On a connected machine fetch {fetch} and set backbone.weights_path=/path/to/it (or "
        f"copy that machine's hub cache into the folder above); or train from scratch with "
        f"backbone.pretrained=false.")


def read_checked_state_dict(path: Path, model: str, skeleton: torch.nn.Module, classifier) -> dict:
    """The state dict in `path` without the classifier, after checking its keys are exactly `skeleton`'s.

    `skeleton` is the full timm model built with num_classes=0. A file of another model (or another depth) fails
    here, naming a few missing and unexpected keys, instead of being loaded in part.
    """
    from timm.models import load_state_dict  # .safetensors or torch file; unwraps 'state_dict'/'model', 'module.'

    try:
        state = load_state_dict(str(path))
    except Exception as err:  # a torch/safetensors reader error says little about which file
        raise ValueError(f"cannot read {path} as a state dict ({type(err).__name__}: {err}). backbone.weights_path "
                         f"takes a .safetensors, .pth or .bin state dict of the full timm model {model!r}.") from err
    classifiers = (classifier,) if isinstance(classifier, str) else tuple(classifier or ())
    state = {k: v for k, v in state.items() if not any(k in (f"{c}.weight", f"{c}.bias") for c in classifiers)}
    expected = set(skeleton.state_dict())
    missing = sorted(expected - set(state))
    unexpected = sorted(set(state) - expected)
    if missing or unexpected:
        raise ValueError(
            f"{path} does not fit timm model {model!r} with these backbone.model_args: {len(missing)} missing keys "
            f"{missing[:4]}, {len(unexpected)} unexpected keys {unexpected[:4]}. Give the state dict of the full "
            f"timm model (as timm publishes it on the hub), not of another model, a features_only model or another "
            f"depth.")
    return state


def size_mismatch_error(err: RuntimeError, path: Path, model: str) -> ValueError:
    """torch's message names every mismatched tensor; keep three and say what to change."""
    lines = [line.strip() for line in str(err).splitlines() if "size mismatch" in line]
    return ValueError(f"{path} has the keys of timm model {model!r} but other tensor sizes ({len(lines)} differ, "
                      f"e.g. {lines[:3]}). ImageNet weights need the published widths: drop the backbone.model_args "
                      f"that change them (dims, embed_dim, num_heads...); a ViT's img_size may differ.")
