"""evaluate.py with a saved gallery: encode the references once into a GalleryIndex, answer queries from it.

    python evaluate.py ckpt=.../best.pt gallery.save=DIR [gallery.backend=faiss gallery.kind=pq_refine]
    python evaluate.py ckpt=.../best.pt gallery.load=DIR      # only the query branch runs

DIR holds `gallery.pt` (GalleryIndex.save), `gallery.json` (what it was built from, and the reference spread) and
the places (`references.jsonl`, `queries.jsonl`: geoloc/tasks/crossview/places.py), which localize.py reads. It is
written whole or not at all, an existing gallery is replaced only with `gallery.overwrite=true`, and a gallery is
loaded only by the weights that built it, for the split it was built from (gallery_folder.py).
Gallery row j is the split's reference j, so the queries must come from the split the gallery was built on; they
are scored against the split's relevance (`geoloc.eval.retrieval_metrics.index_metrics`). With `kind=flat` the
stored vectors go through the scorer itself, so every number equals the exact evaluation, AP included; approximate
kinds are scored from their top-k lists, without AP. The default
`kind=auto` builds `flat` below `auto_exact_below` (100,000) references and `pq_refine` (FAISS; 99.9% of the exact
R@1 at 2 ms per query on 1M references, benchmarks/README.md) from there on; gallery.json records the kind built.
Both ways run the checks of the validation path (geoloc.eval.descriptors): NaN/inf descriptors raise before anything
is saved, and a collapsed gallery reports recall 0 with a warning (the spread of a saved gallery is measured when it
is built; a collapsed one is not saved).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, fields
from pathlib import Path

import torch

from geoloc.config import ConfigError
from geoloc.tasks.crossview.datasets import EvalData
from geoloc.engine import distributed as dist
from geoloc.eval.descriptors import check_descriptors
from geoloc.eval.gallery import KINDS, PQ_KINDS, GalleryIndex, IndexParams, import_faiss, training_points
from geoloc.eval.keys import guarded
from geoloc.eval.retrieval_metrics import index_metrics, split_plan
from geoloc.tasks.crossview.confidence import (NO_HOLDOUT, TOP1, calibrators, confidence_report, fit_top1,
                                               index_answers, uncalibrated, with_positives)
from geoloc.tasks.crossview.encode import encode, encode_images
from geoloc.tasks.crossview.gallery_folder import open_gallery, save_gallery


AUTO_APPROXIMATE = "pq_refine"  # what kind=auto builds for large galleries (benchmarks/README.md, 1M references)


@dataclass
class GalleryConfig(IndexParams):
    """evaluate.py's gallery.* keys: what to build or load, and the index knobs (IndexParams, their one home)."""

    save: str | None = None  # DIR: build the gallery from the split's references and save it there
    overwrite: bool = False  # gallery.save may replace a gallery already in DIR
    load: str | None = None  # DIR: answer the queries from this saved gallery
    backend: str = "torch"  # torch (exact, chunked) | faiss
    kind: str = "auto"  # auto | flat (exact) | ivfpq | pq_refine | ivfpq_refine | hnsw (the last four: faiss)
    auto_exact_below: int = 100_000  # kind=auto: flat below this many references, AUTO_APPROXIMATE (faiss) above

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

    def resolved(self, num_references: int) -> tuple[str, str]:
        """(backend, kind) to build for a gallery of ``num_references``: kind=auto picks flat or AUTO_APPROXIMATE."""
        if self.kind != "auto":
            return self.backend, self.kind
        if num_references < self.auto_exact_below:
            return self.backend, "flat"
        try:
            import_faiss()
        except ImportError as e:
            raise ConfigError(f"gallery.kind=auto builds {AUTO_APPROXIMATE} (faiss) for {num_references:,} references "
                              f"(>= gallery.auto_exact_below={self.auto_exact_below:,}), but faiss is not installed: "
                              "pip install faiss-cpu, or set gallery.kind=flat for exact search") from e
        return "faiss", AUTO_APPROXIMATE


def index_knobs(cfg: GalleryConfig, num_references: int) -> tuple[str, str, IndexParams]:
    """(backend, kind, knobs) to build for `num_references`; a kind that cannot train on so few is refused."""
    backend, kind = cfg.resolved(num_references)
    knobs = {f.name: getattr(cfg, f.name) for f in fields(IndexParams)}
    knobs["nlist"] = max(1, min(cfg.nlist, num_references // 39))
    needed, trains = training_points(kind, knobs)
    if num_references < needed:
        raise ConfigError(f"gallery.kind={cfg.kind} builds {kind}, which trains {trains} and so needs at least "
                          f"{needed} references; this split has {num_references}. Use gallery.kind=flat (exact, "
                          f"and fast at this size)" + (", or fewer gallery.nbits" if kind == "ivfpq" else ""))
    return backend, kind, IndexParams(**knobs)


def build_index(reference: torch.Tensor, cfg: GalleryConfig) -> GalleryIndex:
    backend, kind, knobs = index_knobs(cfg, reference.shape[0])
    if kind in PQ_KINDS and reference.shape[1] % cfg.m:
        raise ConfigError(f"gallery.kind={cfg.kind} builds {kind}, whose gallery.m={cfg.m} sub-quantisers must divide "
                          f"the descriptor dim {reference.shape[1]}: set gallery.m to a divisor of it")
    index = GalleryIndex(reference.shape[1], backend=backend, kind=kind, params=knobs)
    return index.add(reference)


def encode_split(task, engine, data: EvalData, batch_size: int, sides=("query", "reference")) -> dict:
    """{side: descriptors} of the split's queries and / or references, each image through its view's branch."""
    if data.pairs is not None:
        return encode(task, engine, engine.loader(data.pairs, batch_size, train=False), keys=sides)
    encoders = dict(zip(("query", "reference"), task.model.encoders(data.split.aerial_queries)))
    images = {"query": data.queries, "reference": data.references}
    return {side: encode_images(task, engine, engine.loader(images[side], batch_size, train=False), encoders[side])
            for side in sides}


def evaluate(task, engine, data: EvalData, batch_size: int, cfg: GalleryConfig, meta: dict,
             held_out: EvalData | None = None, fov: float = 360.0, run_dir: Path | None = None) -> dict:
    """Build-and-save or load the gallery, then score the split's queries against it. `meta`: what built it, as
    gallery.json records it: `ckpt`, `model_fingerprint` (of the task's weights) and `dataset` (the reader).
    held_out: the labelled queries a saved gallery's confidence is fitted on (confidence.py; None: uncalibrated),
    seen at field of view `fov`. A calibrated gallery adds `ece_top1` and writes run_dir/confidence.png."""
    split = data.split
    if cfg.load:
        saved = open_gallery(cfg.load, meta["model_fingerprint"], meta["ckpt"], device=engine.device, split=split,
                             dataset=meta["dataset"])
        index, spread = saved.index, saved.info["reference_spread"]
        query = encode_split(task, engine, data, batch_size, sides=("query",))["query"]
        check_descriptors(query)
        plan = split_plan(split, exact=index.kind == "flat")
        metrics = guarded(lambda: index_metrics(index, query, split), spread, plan)
        return {**metrics, **scored_confidence(saved.calibration, index, query, split, run_dir),
                "num_references": len(index)}
    index_knobs(cfg, split.num_references)  # a kind that cannot train on this split fails before encoding
    desc = encode_split(task, engine, data, batch_size)
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

    exact = cfg.resolved(split.num_references)[1] == "flat"
    metrics = guarded(build_and_score, spread, split_plan(split, exact=exact))
    if cfg.save and not built:
        warnings.warn(f"gallery.save={cfg.save}: nothing saved, the reference descriptors collapsed")
    confidence = scored_confidence(record, built[0], query, split, run_dir) if built else {}
    return {**metrics, **confidence, "num_references": len(reference)}


def fitted_confidence(task, engine, held_out: EvalData | None, batch_size: int, reference: torch.Tensor,
                      split, fov: float) -> dict:
    """calibration.json's record: the top-1 confidence fitted on the held-out queries against this gallery's
    references (confidence.py), or why there is none."""
    if held_out is None:
        return uncalibrated(NO_HOLDOUT)
    held = encode_split(task, engine, held_out, batch_size)
    check_descriptors(held["query"], held["reference"])
    gallery, rows = with_positives(reference, split.references, held["reference"], held_out.split.references,
                                   held_out.split.positives)
    rule = (f"the last {held_out.split.num_queries} queries of {held_out.split.name} (dataset.calibration_holdout),"
            f" kept out of training, against the {len(split.references)} references of {split.name} plus their "
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
