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

import re
import warnings
from dataclasses import dataclass, fields
from pathlib import Path

import torch
from torch.utils.data import Dataset

from geoloc.config import ConfigError
from geoloc.tasks.crossview.datasets import EvalData, holdout_rule
from geoloc.engine import distributed as dist
from geoloc.engine.sampling import split_key
from geoloc.eval.descriptors import check_descriptors, descriptor_spread, require_finite
from geoloc.eval.search_index import (KINDS, PQ_KINDS, GalleryIndex, IndexParams, import_faiss, sub_quantisers,
                                 training_points, training_rows)
from geoloc.eval.keys import guarded
from geoloc.eval.retrieval_metrics import index_metrics, split_plan
from geoloc.eval.scoring import top_k
from geoloc.gallery.confidence import (NO_HOLDOUT, TOP1, across_jobs, calibrators, confidence_report,
                                               fit_top1, index_answers, uncalibrated, with_positives, with_refiner)
from geoloc.tasks.crossview.encode import encode, encode_images
from geoloc.gallery.folder import open_codebook, open_gallery, save_gallery
from geoloc.tasks.crossview.refine_confidence import fitted_within, scored_refiner


AUTO_APPROXIMATE = "pq_refine"  # what kind=auto builds for large galleries (benchmarks/README.md, 1M references)
AUTO_COMPACT = "pq_sq8"  # ... and when their float32 vectors exceed gallery.max_memory (a quarter of the bytes)
_UNITS = {"": 1, "b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12, "kib": 2**10, "mib": 2**20,
          "gib": 2**30, "tib": 2**40}


def memory_bytes(value: str | int, key: str = "gallery.max_memory") -> int:
    """Bytes of a size given as an integer or a string with a unit: 8GiB, 512MiB, 2GB, 1000000."""
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([a-zA-Z]*)\s*", str(value))
    if not match or match.group(2).lower() not in _UNITS or float(match.group(1)) <= 0:
        raise ValueError(f"{key}={value!r}: give a size such as 8GiB, 512MiB, 2GB or a number of bytes")
    return int(float(match.group(1)) * _UNITS[match.group(2).lower()])


@dataclass
class GalleryConfig(IndexParams):
    """evaluate.py's gallery.* keys: what to build or load, and the index knobs (IndexParams, their one home)."""

    save: str | None = None  # DIR: build the gallery from the split's references and save it there
    overwrite: bool = False  # gallery.save may replace a gallery already in DIR
    load: str | None = None  # DIR: answer the queries from this saved gallery
    backend: str = "torch"  # torch (exact, chunked) | faiss
    kind: str = "auto"  # auto | flat (exact) | ivfpq | pq_refine | ivfpq_refine | pq_sq8 | hnsw (from ivfpq on: faiss)
    auto_exact_below: int = 100_000  # kind=auto: flat below this many references, AUTO_APPROXIMATE (faiss) above
    max_memory: str = "8GiB"  # kind=auto: AUTO_COMPACT when the float32 vectors (N x dim x 4 bytes) exceed this
    train_only: bool = False  # with save: write the trained codebook only (no rows), for gallery.codebook
    codebook: str | None = None  # DIR of a codebook (train_only): the index is filled from it, not trained here
    num_shards: int = 1  # with save: this job encodes one of num_shards contiguous blocks of the references ...
    shard_index: int = 0  # ... block shard_index (0-based); `geoloc gallery merge` joins the shard folders

    def __post_init__(self):
        super().__post_init__()
        if self.save and self.load:
            raise ValueError("give gallery.save=DIR (build) or gallery.load=DIR (query), not both")
        if self.backend not in ("torch", "faiss"):
            raise ValueError(f"gallery.backend must be 'torch' or 'faiss', got {self.backend!r}")
        if self.kind not in ("auto", *KINDS):
            raise ValueError(f"gallery.kind must be one of {('auto', *KINDS)}, got {self.kind!r}")
        if self.kind not in ("auto", "flat") and self.backend != "faiss":
            raise ValueError(f"gallery.kind={self.kind} needs gallery.backend=faiss (torch has only kind=flat)")
        if self.auto_exact_below < 1:
            raise ValueError(f"gallery.auto_exact_below={self.auto_exact_below}: must be >= 1")
        memory_bytes(self.max_memory)
        if not 0 <= self.shard_index < self.num_shards:
            raise ValueError(f"gallery.shard_index={self.shard_index} gallery.num_shards={self.num_shards}: the "
                             f"shard index must be in 0..num_shards-1 (num_shards >= 1)")
        if (self.train_only or self.num_shards > 1 or self.codebook) and not self.save:
            what = ("gallery.train_only=true" if self.train_only else "gallery.num_shards" if self.num_shards > 1
                    else "gallery.codebook")
            raise ValueError(f"{what} writes a folder: give gallery.save=DIR")
        if self.train_only and (self.num_shards > 1 or self.codebook):
            raise ValueError("gallery.train_only=true trains the codebook every shard is filled from: give it "
                             "without gallery.num_shards / gallery.codebook")

    def resolved(self, num_references: int, dim: int) -> tuple[str, str]:
        """(backend, kind) to build for a gallery of ``num_references`` of ``dim``: kind=auto picks flat,
        AUTO_APPROXIMATE or, when the float32 vectors would not fit in max_memory, AUTO_COMPACT."""
        if self.kind != "auto":
            return self.backend, self.kind
        if num_references < self.auto_exact_below:
            return self.backend, "flat"
        kind = AUTO_APPROXIMATE if num_references * dim * 4 <= memory_bytes(self.max_memory) else AUTO_COMPACT
        try:
            import_faiss()
        except ImportError as e:
            raise ConfigError(f"gallery.kind=auto builds {kind} (faiss) for {num_references:,} references "
                              f"(>= gallery.auto_exact_below={self.auto_exact_below:,}), but faiss is not installed: "
                              "pip install faiss-cpu, or set gallery.kind=flat for exact search") from e
        return "faiss", kind


def index_knobs(cfg: GalleryConfig, num_references: int, dim: int) -> tuple[str, str, IndexParams]:
    """(backend, kind, knobs) to build for `num_references` of `dim`; a kind that cannot train on so few, or whose
    sub-quantisers do not divide `dim`, is refused."""
    backend, kind = cfg.resolved(num_references, dim)
    knobs = {f.name: getattr(cfg, f.name) for f in fields(IndexParams)}
    knobs["nlist"] = max(1, min(cfg.nlist, num_references // 39))
    needed, trains = training_points(kind, knobs)
    if num_references < needed:
        raise ConfigError(f"gallery.kind={cfg.kind} builds {kind}, which trains {trains} and so needs at least "
                          f"{needed} references; this split has {num_references}. Use gallery.kind=flat (exact, "
                          f"and fast at this size)" + (", or fewer gallery.nbits" if kind == "ivfpq" else ""))
    knob, m = sub_quantisers(kind, knobs) if kind in PQ_KINDS else ("m", 1)
    if dim % m:
        raise ConfigError(f"gallery.kind={cfg.kind} builds {kind}, whose gallery.{knob}={m} sub-quantisers must "
                          f"divide the descriptor dim {dim}: set gallery.{knob} to a divisor of it")
    return backend, kind, IndexParams(**knobs)


def empty_index(cfg: GalleryConfig, num_references: int, dim: int) -> GalleryIndex:
    backend, kind, knobs = index_knobs(cfg, num_references, dim)
    return GalleryIndex(dim, backend=backend, kind=kind, params=knobs)


def build_index(reference: torch.Tensor, cfg: GalleryConfig) -> GalleryIndex:
    return empty_index(cfg, reference.shape[0], reference.shape[1]).add(reference)


def shard_rows(num_references: int, num_shards: int, shard_index: int) -> range:
    """The references shard `shard_index` of `num_shards` encodes: a contiguous block, the blocks in order."""
    return range(num_references * shard_index // num_shards, num_references * (shard_index + 1) // num_shards)


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
    if data.pairs is not None:
        return encode(task, engine, engine.loader(subset(data.pairs), batch_size, train=False), keys=sides,
                      refine=refine)
    encoders = dict(zip(("query", "reference"), task.model.encoders(data.split.aerial_queries)))
    images = {"query": data.queries, "reference": subset(data.references)}
    out = {}
    for side in sides:
        out.update(encode_images(task, engine, engine.loader(images[side], batch_size, train=False), encoders[side],
                                 side, refine))
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


def top1_rows(index: GalleryIndex, query: torch.Tensor):
    """() -> (Q,) each query's top-1 row in `index`: the gallery's answer, where a refiner's end-to-end metres
    need it (refine.fine_metrics)."""
    return lambda: index.search(query, 1)[1][:, 0].numpy()


def build_part(task, engine, data: EvalData, batch_size: int, cfg: GalleryConfig, meta: dict,
               held_out: EvalData | None = None) -> dict:
    """Write a part of a gallery built across jobs: the codebook (train_only), or the index of one shard of the
    references (or of all of them, num_shards=1) filled from gallery.codebook; shard 0 also its calibration.json
    (shard_calibration, from the `held_out` queries). Nothing is scored: the merged gallery is (`geoloc gallery
    merge`, then evaluate.py gallery.load=)."""
    split, dim = data.split, task.model_cfg.dim
    index = empty_index(cfg, split.num_references, dim)
    codebook = None
    if cfg.codebook:
        codebook = open_codebook(cfg.codebook, meta["model_fingerprint"], meta["ckpt"], split, meta["dataset"],
                                 kind=index.kind, params=index.params)
        index = codebook.index.trained_empty()
    elif not cfg.train_only and not index.is_trained:
        raise ConfigError(f"gallery.kind={cfg.kind} builds {index.kind}, which trains a codebook, and each shard "
                          f"must be filled from the same one: build it once with gallery.train_only=true "
                          f"gallery.save=CODEBOOK_DIR, then give gallery.codebook=CODEBOOK_DIR to every shard job")
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


def scored_confidence(record: dict | None, index: GalleryIndex, query: torch.Tensor, split,
                      run_dir: Path | None) -> dict:
    """{"ece_top1"} of the split's queries under the gallery's calibrator, and run_dir/confidence.png; {} when the
    gallery is uncalibrated."""
    calibrator = calibrators(record).get(TOP1)
    if calibrator is None:
        return {}
    features, right = index_answers(index, query, split.positives)
    figure = Path(run_dir) / "confidence.png" if run_dir is not None and dist.is_main() else None
    return confidence_report(calibrator, features, right, figure)
