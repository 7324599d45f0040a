"""Descriptors of a whole dataset, through the engine's public loader (DDP-sharded, then gathered in order)."""

from __future__ import annotations

import copy

import torch

from geoloc.engine import distributed as dist


def encode(task, engine, loader, encoders: dict | None = None, refine: bool = False, entry: str | None = None) -> dict:
    """{side: N x dim float32 CPU descriptors} of the whole dataset of `loader` (an unshuffled engine.loader) in
    dataset order, as `described` gives them: by default the pairs' "query" and "reference" through their branches
    of `task.model`; a ViewImages loader with entry="image" and {side: its encoder}. refine: also the refiner's maps."""
    encoders = encoders or {side: getattr(task.model, side) for side in ("query", "reference")}
    return _encoded(task, engine, loader, lambda batch: described(task, batch, encoders, refine, entry))


def described(task, batch: dict, encoders: dict, refine: bool = False, entry: str | None = None,
              keep: tuple[str, ...] = ()) -> dict:
    """{side: encoders[side](the side's images)} of one batch, for each side of `encoders` ("query", "reference"):
    a batch of pairs holds each side's images under the side's name, a ViewImages batch (one side) under `entry`
    ("image"). refine: also {"refine_<side>": `task.refiner`'s maps of the same items at its input (the entry
    "refine_<side>" / "refine_<entry>")} and the queries' "refine_heading". keep: the entries of a batch of queries
    passed on as they are (a heading search's true "heading"). Validation and the gallery both encode through it."""
    out = {side: encoder(batch[entry or side]) for side, encoder in encoders.items()}
    if refine:
        out.update({f"refine_{s}": refine_encoder(task, s)(batch[f"refine_{entry or s}"]) for s in encoders})
        keep = (*keep, "refine_heading")
    return {**out, **{k: batch[k] for k in (keep if "query" in encoders else ())}}


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
