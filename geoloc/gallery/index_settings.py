"""The build settings of a saved gallery, which know no method: evaluate.py's `gallery.*` keys (GalleryConfig), the
kind `gallery.kind=auto` picks for a gallery's size and memory, the index knobs checked against the references
before anything is encoded, the block of references one shard job encodes, and the scoring of a gallery's top-1
confidence. The cross-view task encodes the references and calls these (tasks/crossview/gallery_build.py)."""

from __future__ import annotations

import re
from dataclasses import dataclass, fields
from pathlib import Path

import torch

from geoloc.config import ConfigError
from geoloc.engine import distributed as dist
from geoloc.eval.index_kinds import KINDS, PQ_KINDS, IndexParams, import_faiss, sub_quantisers, training_points
from geoloc.eval.search_index import GalleryIndex
from geoloc.gallery.confidence import TOP1, calibrators, confidence_report, index_answers


AUTO_APPROXIMATE = "pq_refine"  # what kind=auto builds for large galleries (benchmarks/README.md, 1M references)
AUTO_COMPACT = "pq_sq8"  # ... and when their float32 vectors exceed gallery.max_memory (a quarter of the bytes)
AUTO_DISK = "ivfpq_disk"  # ... and when even pq_sq8's (dim + 16 bytes a reference) would: 40 bytes, the rest on disk
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
    kind: str = "auto"  # auto | flat (exact) | ivfpq | pq_refine | ivfpq_refine | pq_sq8 | ivfpq_disk | hnsw (from
    # ivfpq on: faiss)
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
        AUTO_APPROXIMATE or, when the float32 vectors would not fit in max_memory, AUTO_COMPACT, and AUTO_DISK when
        not even its codes would."""
        if self.kind != "auto":
            return self.backend, self.kind
        if num_references < self.auto_exact_below:
            return self.backend, "flat"
        budget = memory_bytes(self.max_memory)
        kind = (AUTO_APPROXIMATE if num_references * dim * 4 <= budget else
                AUTO_COMPACT if num_references * (dim + 16) <= budget else AUTO_DISK)
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
    knobs = requested_knobs(cfg)
    knobs["nlist"] = capped_nlist(cfg.nlist, num_references)
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


def capped_nlist(nlist: int, num_references: int) -> int:
    """The inverted lists an IVF kind trains on `num_references`: at most one per 39 of them (FAISS's minimum
    training points per list)."""
    return max(1, min(nlist, num_references // 39))


def requested_knobs(cfg: GalleryConfig) -> dict:
    """The index knobs as gallery.* gives them (nlist before it is capped by the references a codebook trains on)."""
    return {f.name: getattr(cfg, f.name) for f in fields(IndexParams)}


def empty_index(cfg: GalleryConfig, num_references: int, dim: int) -> GalleryIndex:
    backend, kind, knobs = index_knobs(cfg, num_references, dim)
    return GalleryIndex(dim, backend=backend, kind=kind, params=knobs)


def build_index(reference: torch.Tensor, cfg: GalleryConfig) -> GalleryIndex:
    return empty_index(cfg, reference.shape[0], reference.shape[1]).add(reference)


def shard_rows(num_references: int, num_shards: int, shard_index: int) -> range:
    """The references shard `shard_index` of `num_shards` encodes: a contiguous block, the blocks in order."""
    return range(num_references * shard_index // num_shards, num_references * (shard_index + 1) // num_shards)


def top1_rows(index: GalleryIndex, query: torch.Tensor):
    """() -> (Q,) each query's top-1 row in `index`: the gallery's answer, where a refiner's end-to-end metres
    need it (refine.fine_metrics)."""
    return lambda: index.search(query, 1)[1][:, 0].numpy()


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
