"""The image sizes MMDIP's networks take, checked when the config is parsed, before phase 1 starts.

Phase 2's U-Net generator needs H and W divisible by 2**task.translation.num_downs and its PatchGAN a map left
after task.translation.d_layers halvings; phase 1's segmenter has its own rule (FCN-8s: multiples of 32, a U-Net
segmenter: of 2**num_downs). Found only when phase 2 starts, a size that does not fit would cost all of phase 1,
and a run cannot start from phase 1's weights. Each network runs once on the meta device (shapes only, no memory,
no random numbers) at dataset.image_size and its phase's batch size.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from geoloc.config import ConfigError
from geoloc.tasks.mmdip.mmdip_config import DynamicDataConfig, MMDIPConfig
from geoloc.tasks.mmdip.networks import (
    build_discriminator,
    build_generator,
    build_segmenter,
    generator_channels,
)

SHOWN_SIDES = 6  # how many fitting sides an error lists


@dataclass(frozen=True)
class PhaseNetwork:
    what: str  # e.g. "phase 2's generator (a U-Net)"
    keys: dict[str, object]  # the config keys that set its shape rule, with their values
    build: Callable[[], nn.Module]
    channels: int
    batch: int
    hint: str = ""  # another value of `keys` that takes the size asked for, when there is one


def phase_networks(task_cfg: MMDIPConfig, size: tuple[int, int]) -> list[PhaseNetwork]:
    """The networks phases 1 and 2 train (phase 2 also trains phase 1's segmenter, at phase 1's size)."""
    seg, tr, k = task_cfg.segmentation, task_cfg.translation, task_cfg.num_classes
    own = seg.segmenter_keys.get(seg.model, {})
    seg_keys = {"task.segmentation.model": seg.model,
                **{f"task.segmentation.{seg.model}.{key}": value for key, value in own.items()}}
    return [
        PhaseNetwork("phase 1's segmenter", seg_keys, lambda: build_segmenter(seg, k), 3,
                     min(seg.batch_size, tr.batch_size)),
        PhaseNetwork("phase 2's generator (a U-Net: H and W multiples of 2**num_downs)",
                     {"task.translation.num_downs": tr.num_downs}, lambda: build_generator(tr, k),
                     generator_channels(tr.variant, k), tr.batch_size, _fitting_depth(tr.num_downs, size)),
        PhaseNetwork("phase 2's discriminator (a PatchGAN)", {"task.translation.d_layers": tr.d_layers},
                     lambda: build_discriminator(tr), 6, tr.batch_size),
    ]


def check_image_size(task_cfg: MMDIPConfig, data_cfg: DynamicDataConfig) -> None:
    """Refuse a dataset.image_size that a network of phase 1 or 2 cannot take, naming both keys and the sides
    that network takes."""
    h, w = data_cfg.image_size
    for net in phase_networks(task_cfg, (h, w)):
        problem = _problem(net, h, w)
        if problem is None:
            continue
        largest = max(256, 2 * max(h, w))
        fits = [s for s in range(16, largest + 1, 8) if _problem(net, s, s) is None]
        if not fits:  # it runs at no size on the meta device (a plug-in's): this check cannot tell
            continue
        shown = ", ".join(map(str, fits[:SHOWN_SIDES])) + (" and more" if len(fits) > SHOWN_SIDES else "")
        keys = ", ".join(f"{key}={value}" for key, value in net.keys.items())
        raise ConfigError(
            f"dataset.image_size={[h, w]} does not fit {net.what}, set by {keys}: {problem.rstrip('.')}. Sides it "
            f"takes (each of H and W, multiples of 8 up to {largest}): {shown}. Change dataset.image_size or "
            f"{' / '.join(net.keys)}{net.hint}. Nothing was trained.")


def _fitting_depth(num_downs: int, size: tuple[int, int]) -> str:
    depth = num_downs
    while depth > 2 and (size[0] % 2**depth or size[1] % 2**depth):
        depth -= 1
    fits = depth < num_downs and not (size[0] % 2**depth or size[1] % 2**depth)
    return f" (num_downs={depth} takes {size[0]}x{size[1]})" if fits else ""


def _problem(net: PhaseNetwork, h: int, w: int) -> str | None:
    """None when `net`, in training mode, maps a batch of h x w images; else the error it raises."""
    try:
        with torch.device("meta"):
            module = net.build().train()
            module(torch.empty(net.batch, net.channels, h, w))
    except Exception as err:  # noqa: BLE001  (any failure at this size is the answer)
        return f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
    return None
