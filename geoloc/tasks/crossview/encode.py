"""Descriptors of a whole dataset, through the engine's public loader (DDP-sharded, then gathered in order)."""

from __future__ import annotations

import copy

import torch

from geoloc.engine import distributed as dist


@torch.no_grad()
def encode(task, engine, loader, keys=("query", "reference")) -> dict:
    """{key: N x dim float32 CPU descriptors} of the whole dataset of `loader` (an unshuffled engine.loader) in
    dataset order.

    keys name both the batch entry and the branch of `task.model` that encodes it ("query", "reference").
    """
    was_training = task.training
    task.eval()
    parts: dict[str, list[torch.Tensor]] = {k: [] for k in (*keys, "index")}
    for batch in loader:
        batch = engine.to_device(batch)
        with engine.autocast():
            for key in keys:
                parts[key].append(getattr(task.model, key)(batch[key]).float())
        parts["index"].append(batch["index"])
    out = {k: dist.all_gather_variable(torch.cat(v)) for k, v in parts.items()}
    order = torch.argsort(out.pop("index"))
    task.train(was_training)
    return {k: v[order].cpu() for k, v in out.items()}


@torch.no_grad()
def encode_images(task, engine, loader, encoder) -> torch.Tensor:
    """N x dim float32 CPU descriptors of a ViewImages loader's images (batch["image"]) through `encoder` (a branch
    of `task.model`: `task.model.encoders(...)` picks it), in dataset order."""
    was_training = task.training
    task.eval()
    descriptors, order = [], []
    for batch in loader:
        batch = engine.to_device(batch)
        with engine.autocast():
            descriptors.append(encoder(batch["image"]).float())
        order.append(batch["index"])
    out, index = dist.all_gather_variable(torch.cat(descriptors)), dist.all_gather_variable(torch.cat(order))
    task.train(was_training)
    return out[torch.argsort(index)].cpu()


def plain_pairs_loader(engine, pairs, batch_size: int):
    """A loader over the training pairs without augmentation, for a similarity sampler's descriptors each epoch
    (built once: with persistent workers, a new loader per epoch would start its workers again)."""
    plain = copy.copy(pairs)
    plain.train = False
    return engine.loader(plain, batch_size, train=False)
