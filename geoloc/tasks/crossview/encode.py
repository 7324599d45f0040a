"""Descriptors of a whole dataset, through the engine's public loader (DDP-sharded, then gathered in order)."""

from __future__ import annotations

import copy

import torch

from geoloc.engine import distributed as dist


def encode(task, engine, loader, keys=("query", "reference"), refine: bool = False) -> dict:
    """{key: N x dim float32 CPU descriptors} of the whole dataset of `loader` (an unshuffled engine.loader) in
    dataset order.

    keys name both the batch entry and the branch of `task.model` that encodes it ("query", "reference").
    refine: also {"refine_<key>": `task.refiner`'s maps of batch["refine_<key>"]}, the same items read at the
    refiner's input (datasets.eval_sets(refine=)), from the same decode, and with the queries their
    "refine_heading" (the heading each was read at, the truth of the refiner's).
    """
    def describe(batch):
        out = {k: getattr(task.model, k)(batch[k]) for k in keys}
        if refine:
            out.update({f"refine_{k}": refine_encoder(task, k)(batch[f"refine_{k}"]) for k in keys})
            out.update(query_heading(batch, keys))
        return out

    return _encoded(task, engine, loader, describe)


def encode_images(task, engine, loader, encoder, side: str, refine: bool = False) -> dict:
    """{side: N x dim float32 CPU descriptors} of a ViewImages loader's images (batch["image"]) through `encoder` (a
    branch of `task.model`: `task.model.encoders(...)` picks it), in dataset order; refine: also {"refine_<side>":
    the refiner's maps of the same images at its input (batch["refine_image"]) and the queries' "refine_heading"},
    from the same decode."""
    def describe(batch):
        out = {side: encoder(batch["image"])}
        if refine:
            out[f"refine_{side}"] = refine_encoder(task, side)(batch["refine_image"])
            out.update(query_heading(batch, (side,)))
        return out

    return _encoded(task, engine, loader, describe)


def query_heading(batch, sides) -> dict:
    """{"refine_heading": the heading each query of the batch was read at for the refiner} where `sides` holds the
    queries, else {}."""
    return {"refine_heading": batch["refine_heading"]} if "query" in sides else {}


def refine_encoder(task, side: str):
    """The encoder of `task.refiner` for a query ("query") or a tile ("reference")."""
    return {"query": task.refiner.encode_query, "reference": task.refiner.encode_reference}[side]


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
