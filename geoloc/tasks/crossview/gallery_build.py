"""evaluate.py with a saved gallery: encode the references once into a GalleryIndex, answer queries from it.

    python evaluate.py ckpt=.../best.pt gallery.save=DIR [gallery.backend=faiss gallery.kind=pq_refine]
    python evaluate.py ckpt=.../best.pt gallery.load=DIR      # only the query branch runs

A gallery too large for one job is built in parts (docs/distributed.md): the codebook once
(`gallery.train_only=true gallery.save=CODEBOOK`: the trained quantisers, no rows, from the references
`training_rows` picks), then each of `gallery.num_shards` jobs encodes its contiguous block of references
(`gallery.shard_index=i gallery.codebook=CODEBOOK gallery.save=SHARD_i`), then `geoloc gallery merge SHARD_0 ...
out=DIR` joins them (geoloc/gallery/shards.py). A kind that trains nothing (flat) needs no codebook.

DIR holds `gallery.pt` (GalleryIndex.save), `gallery.json` (what it was built from, and the reference spread) and
the places (`references.jsonl`, `queries.jsonl`: geoloc/gallery/places.py), which localize.py reads. It is
written whole or not at all, an existing gallery is replaced only with `gallery.overwrite=true`, and a gallery is
loaded only by the weights that built it, for the split it was built from (geoloc/gallery/folder.py).
Gallery row j is the split's reference j, so the queries must come from the split the gallery was built on; they
are scored against the split's relevance (`geoloc.eval.retrieval_metrics.index_metrics`). With `kind=flat` the
stored vectors go through the scorer itself, so every number equals the exact evaluation, AP included; approximate
kinds are scored from their top-k lists, without AP. The default
`kind=auto` builds `flat` below `auto_exact_below` (100,000) references and, from there on, `pq_refine` (FAISS; 99.9% of
the exact R@1 at 2 ms per query on 1M references, benchmarks/README.md) while its float32 vectors fit in
`max_memory`, `pq_sq8` (a quarter of the bytes) when they do not; gallery.json records the kind built.
Both ways run the checks of the validation path (geoloc.eval.descriptors): NaN/inf descriptors raise before anything
is saved, and a collapsed gallery reports recall 0 with a warning (the spread of a saved gallery is measured when it
is built; a collapsed one is not saved).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
from torch.utils.data import Dataset

from geoloc.config import ConfigError
from geoloc.engine import distributed as dist
from geoloc.engine.sampling import split_key
from geoloc.eval.descriptors import check_descriptors, descriptor_spread, require_finite
from geoloc.eval.keys import guarded
from geoloc.eval.retrieval_metrics import index_metrics, split_plan
from geoloc.eval.scoring import top_k
from geoloc.eval.index_kinds import training_rows
from geoloc.gallery.confidence import NO_HOLDOUT, across_jobs, fit_top1, uncalibrated, with_positives, with_refiner
from geoloc.gallery.folder import open_codebook, open_gallery, save_gallery
from geoloc.gallery.index_settings import (GalleryConfig, build_index, empty_index, index_knobs, requested_knobs,
                                           scored_confidence, shard_rows, top1_rows)
from geoloc.tasks.crossview.datasets import EvalData, holdout_rule
from geoloc.tasks.crossview.encode import encode
from geoloc.tasks.crossview.refine_confidence import fitted_within, scored_refiner

__all__ = ["GalleryConfig", "build_index", "build_part", "encode_split", "evaluate"]  # GalleryConfig, build_index:
# their home is geoloc/gallery/index_settings.py; imported from here before it


def encode_split(task, engine, data: EvalData, batch_size: int, sides=("query", "reference"),
                 rows=None, refine: bool = False) -> dict:
    """{side: descriptors} of the split's queries and / or references, each image through its view's branch;
    `rows` (ascending): only those references (one-to-one splits: those pairs), in that order. refine (a task with
    a refiner, `data` read with its inputs): also {"refine_<side>": the refiner's maps}, from the same decode."""
    def subset(dataset):
        return dataset if rows is None else Rows(dataset, list(rows))

    if data.pairs is not None and rows is not None:
        labels = data.split.labels()
        if any(int(labels[i]) != i for i in rows):  # pair i holds reference labels[i]
            raise ValueError("encoding some references of a split through its pairs needs pair i to hold "
                             "reference i (a one-to-one split)")
    encoders = dict(zip(("query", "reference"), task.model.encoders(data.split.aerial_queries)))
    if data.pairs is not None:
        return encode(task, engine, engine.loader(subset(data.pairs), batch_size, train=False),
                      {side: encoders[side] for side in sides}, refine)
    images = {"query": data.queries, "reference": subset(data.references)}
    out = {}
    for side in sides:
        out.update(encode(task, engine, engine.loader(images[side], batch_size, train=False), {side: encoders[side]},
                          refine, "image"))
    return out


class Rows(Dataset):
    """The items `rows` of `dataset`, keyed as the engine's sampler keys items (an index or (index, epoch)); each
    item keeps its own "index" in `dataset`, by which encode() orders the descriptors."""

    def __init__(self, dataset, rows: list[int]):
        self.dataset, self.rows = dataset, rows

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, key) -> dict:
        index, epoch = split_key(key)
        return self.dataset[(self.rows[index], epoch)]


def evaluate(task, engine, data: EvalData, batch_size: int, cfg: GalleryConfig, meta: dict,
             held_out: EvalData | None = None, fov: float = 360.0, run_dir: Path | None = None) -> dict:
    """Build-and-save or load the gallery, then score the split's queries against it. `meta`: what built it, as
    gallery.json records it: `ckpt`, `model_fingerprint` (of the task's weights) and `dataset` (the reader).
    held_out: the labelled queries a saved gallery's confidence is fitted on (geoloc/gallery/confidence.py; None: uncalibrated),
    seen at field of view `fov`. A calibrated gallery adds `ece_top1` and writes run_dir/confidence.png."""
    split = data.split
    if cfg.train_only or cfg.num_shards > 1 or cfg.codebook:
        return build_part(task, engine, data, batch_size, cfg, meta, held_out)
    if cfg.load:
        saved = open_gallery(cfg.load, meta["model_fingerprint"], meta["ckpt"], device=engine.device, split=split,
                             dataset=meta["dataset"])
        index, spread = saved.index, saved.info["reference_spread"]
        refine = task.refiner is not None  # the refiner's maps of the tiles too: the references decoded once
        desc = encode_split(task, engine, data, batch_size, sides=("query", "reference") if refine else ("query",),
                            refine=refine)
        query = desc["query"]
        check_descriptors(query)
        plan = split_plan(split, exact=index.kind == "flat")
        metrics = guarded(lambda: index_metrics(index, query, split), spread, plan)
        return {**metrics, **scored_confidence(saved.calibration, index, query, split, run_dir),
                **scored_refiner(saved.calibration, task, split, desc, top1_rows(index, query), run_dir),
                "num_references": len(index)}
    index_knobs(cfg, split.num_references, task.model_cfg.dim)  # a kind that cannot train fails before encoding
    desc = encode_split(task, engine, data, batch_size, refine=task.refiner is not None)
    query, reference = desc["query"], desc["reference"]
    spread = check_descriptors(query, reference)  # raises before a broken gallery is saved

    record = fitted_confidence(task, engine, held_out, batch_size, reference, split, fov) if cfg.save else None
    built = []

    def build_and_score() -> dict:  # not called on a collapse: such a gallery is not worth saving
        index = build_index(reference, cfg)
        built.append(index)
        if cfg.save and dist.is_main():
            save_gallery(cfg.save, index, split, {**meta, "reference_spread": spread}, overwrite=cfg.overwrite,
                         calibration=record)
        return index_metrics(index, query, split)

    exact = cfg.resolved(split.num_references, reference.shape[1])[1] == "flat"
    metrics = guarded(build_and_score, spread, split_plan(split, exact=exact))
    if cfg.save and not built:
        warnings.warn(f"gallery.save={cfg.save}: nothing saved, the reference descriptors collapsed")
    confidence = scored_confidence(record, built[0], query, split, run_dir) if built else {}
    # a collapsed gallery was not built: its queries' top-1 tiles are then the exact ranking's, as validation's
    top1 = top1_rows(built[0], query) if built else lambda: top_k(query, reference, 1)[1][:, 0].numpy()
    return {**metrics, **confidence, **scored_refiner(record, task, split, desc, top1, run_dir),
            "num_references": len(reference)}


def build_part(task, engine, data: EvalData, batch_size: int, cfg: GalleryConfig, meta: dict,
               held_out: EvalData | None = None) -> dict:
    """Write a part of a gallery built across jobs: the codebook (train_only), or the index of one shard of the
    references (or of all of them, num_shards=1) filled from gallery.codebook; shard 0 also its calibration.json
    (shard_calibration, from the `held_out` queries). Nothing is scored: the merged gallery is (`geoloc gallery
    merge`, then evaluate.py gallery.load=)."""
    split, dim = data.split, task.model_cfg.dim
    codebook = None
    if cfg.codebook:  # its kind and knobs, whatever this split's size (new references appended to a gallery)
        codebook = open_codebook(cfg.codebook, meta["model_fingerprint"], meta["ckpt"],
                                 kind=None if cfg.kind == "auto" else cfg.kind, params=requested_knobs(cfg))
        index = codebook.index.trained_empty()
    else:
        index = empty_index(cfg, split.num_references, dim)
        if not cfg.train_only and not index.is_trained:
            raise ConfigError(f"gallery.kind={cfg.kind} builds {index.kind}, which trains a codebook, and each shard "
                              f"must be filled from the same one: build it once with gallery.train_only=true "
                              f"gallery.save=CODEBOOK_DIR, then give gallery.codebook=CODEBOOK_DIR to every shard "
                              f"job")
    if cfg.train_only:
        if index.is_trained:
            raise ConfigError(f"gallery.kind={cfg.kind} builds {index.kind}, which trains nothing: build the shards "
                              "without a codebook (no gallery.train_only / gallery.codebook)")
        sample = training_rows(split.num_references)
        rows = range(split.num_references) if sample is None else sorted(sample.tolist())
        reference = encode_split(task, engine, data, batch_size, sides=("reference",), rows=rows)["reference"]
        if sample is not None:  # k-means sees the sample in the order a whole gallery's training sees it
            reference = reference[torch.argsort(torch.argsort(sample))]
        require_finite(reference, "reference")
        index.train(reference)
        part, moments, calibration = {"role": "codebook"}, None, None
    else:
        rows = shard_rows(split.num_references, cfg.num_shards, cfg.shard_index)
        reference = encode_split(task, engine, data, batch_size, sides=("reference",), rows=rows)["reference"]
        require_finite(reference, "reference")
        index.add(reference)
        part = {"role": "shard", "shard_index": cfg.shard_index, "num_shards": cfg.num_shards,
                "start": rows.start, "stop": rows.stop}
        # the merge computes the whole gallery's spread (descriptor_spread) from every shard's moments
        r64 = reference.double()
        moments = {"sum": r64.sum(0).tolist(), "sum_sq": (r64 * r64).sum(0).tolist()}
        calibration = shard_calibration(task, engine, held_out, batch_size) if cfg.shard_index == 0 else None
    if dist.is_main():
        record = {**meta, "reference_spread": descriptor_spread(reference) if len(reference) > 1 else 0.0,
                  "part": {**part, "split_references": split.num_references}, "reference_moments": moments,
                  "codebook_sha256": None if codebook is None else codebook.info["codebook_sha256"]}
        save_gallery(cfg.save, index, split, record, overwrite=cfg.overwrite,
                     rows=range(0) if cfg.train_only else rows, calibration=calibration)
    return {"num_references": len(index)}


def shard_calibration(task, engine, held_out: EvalData | None, batch_size: int) -> dict:
    """calibration.json of a shard, which the merge keeps (confidence.across_jobs): the refiner's "within_5m", which
    does not depend on the gallery, fitted on the held-out queries as a one-job save fits it; the top-1 confidence
    uncalibrated, as it needs the whole gallery."""
    held = (None if held_out is None or task.refiner is None else
            encode_split(task, engine, held_out, batch_size, refine=True))
    within = fitted_within(task, held_out, held)
    return across_jobs(None if within is None else with_refiner({}, within))


def fitted_confidence(task, engine, held_out: EvalData | None, batch_size: int, reference: torch.Tensor,
                      split, fov: float) -> dict:
    """calibration.json's record: the top-1 confidence fitted on the held-out queries against this gallery's
    references (geoloc/gallery/confidence.py), or why there is none; with a refiner, its "within_5m" too
    (refine_confidence.py)."""
    held = None if held_out is None else encode_split(task, engine, held_out, batch_size,
                                                      refine=task.refiner is not None)
    record = top1_confidence(held_out, held, reference, split, fov)
    within = fitted_within(task, held_out, held)
    return record if within is None else with_refiner(record, within)


def top1_confidence(held_out: EvalData | None, held: dict | None, reference: torch.Tensor, split,
                    fov: float) -> dict:
    """The top-1 record of the held-out queries' descriptors `held` (encode_split), or why there is none."""
    if held_out is None:
        return uncalibrated(NO_HOLDOUT)
    check_descriptors(held["query"], held["reference"])
    gallery, rows = with_positives(reference, split.references, held["reference"], held_out.split.references,
                                   held_out.split.positives)
    rule = holdout_rule(held_out.split, f"against the {len(split.references)} references of {split.name} plus their "
                                        "own positives")
    return fit_top1(held["query"], gallery, rows, fov, rule)
