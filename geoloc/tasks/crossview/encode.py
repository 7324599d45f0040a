"""Descriptors of a whole dataset, through the engine's public loader (DDP-sharded, then gathered in order)."""

from __future__ import annotations

import copy

import torch

from geoloc.engine import distributed as dist


def encode(task, engine, loader, keys=("query", "reference")) -> dict:
    """{key: N x dim float32 CPU descriptors} of the whole dataset of `loader` (an unshuffled engine.loader) in
    dataset order.

    keys name both the batch entry and the branch of `task.model` that encodes it ("query", "reference").
    """
    return _encoded(task, engine, loader, lambda batch: {k: getattr(task.model, k)(batch[k]) for k in keys})


def encode_images(task, engine, loader, encoder) -> torch.Tensor:
    """N x dim float32 CPU descriptors of a ViewImages loader's images (batch["image"]) through `encoder` (a branch
    of `task.model`: `task.model.encoders(...)` picks it), in dataset order."""
    return _encoded(task, engine, loader, lambda batch: {"image": encoder(batch["image"])})["image"]


@torch.no_grad()
def _encoded(task, engine, loader, describe) -> dict:
    """{key: descriptors} of `describe(batch)` over the loader, in eval mode, gathered over ranks, in dataset
    order (by batch["index"]), as float32 on the CPU."""
    was_training = task.training
    task.eval()
    parts: dict[str, list[torch.Tensor]] = {"index": []}
    for batch in loader:
        batch = engine.to_device(batch, task)
        with engine.autocast():
            for key, value in describe(batch).items():
                parts.setdefault(key, []).append(value.float())
        parts["index"].append(batch["index"])
    out = {k: dist.all_gather_variable(torch.cat(v)) for k, v in parts.items()}
    order = torch.argsort(out.pop("index"))
    task.train(was_training)
    return {k: v[order].cpu() for k, v in out.items()}


def plain_pairs_loader(engine, pairs, batch_size: int):
    """A loader over the training pairs without augmentation, for a similarity sampler's descriptors each epoch
    (built once: with persistent workers, a new loader per epoch would start its workers again)."""
    plain = copy.copy(pairs)
    plain.train = False
    return engine.loader(plain, batch_size, train=False)


def encode_refine_maps(task, engine, data, batch_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(query maps, reference maps) of an EvalData read with the refiner's inputs (datasets.eval_sets(refine=)),
    through `task.refiner`'s two encoders, in dataset order: one-to-one pairs give reference i for query i."""
    refiner = task.refiner
    if data.pairs is not None:
        out = _encoded(task, engine, engine.loader(data.pairs, batch_size, train=False),
                       lambda batch: {"query": refiner.encode_query(batch["refine_query"]),
                                      "reference": refiner.encode_reference(batch["refine_reference"])})
        return out["query"], out["reference"]
    sides = ((data.queries, refiner.encode_query), (data.references, refiner.encode_reference))
    query, reference = (_encoded(task, engine, engine.loader(images, batch_size, train=False),
                                 lambda batch, encoder=encoder: {"map": encoder(batch["refine_image"])})["map"]
                        for images, encoder in sides)
    return query, reference
