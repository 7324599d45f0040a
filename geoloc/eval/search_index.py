"""A gallery of reference descriptors searchable by inner product: built once, saved, queried later.

Two backends:
- ``torch``: exact, the scorer's top-k (`geoloc.eval.scoring.top_k`: chunked, one memory budget, the lower row
  first among equal scores); runs on the device the descriptors live on (GPU when there is one).
- ``faiss`` (the optional ``faiss-cpu`` extra), one ``kind`` each (benchmarks/README.md measures them at 1M):
  - ``flat``: exact (``IndexFlatIP``).
  - ``ivfpq``: inverted lists + 8-bit product quantisation (``IndexIVFPQ``); approximate scores, least memory.
  - ``pq_refine``: every reference scanned as a 4-bit fast-scan PQ code (``IndexPQFastScan``), then the best
    ``k_factor * k`` re-ranked by their exact inner products (``IndexRefineFlat``; Jegou et al., "Searching in
    one billion vectors: re-rank with source coding", ICASSP 2011).
  - ``ivfpq_refine``: the same with inverted lists in front (``IndexIVFPQFastScan``): only ``nprobe`` of ``nlist``
    lists are scanned.
  - ``pq_sq8``: the compact kind: every reference scanned as a 4-bit fast-scan PQ code of ``coarse_m``
    sub-quantisers (``coarse_m / 2`` bytes), the best ``k_factor * k`` re-ranked from 8-bit scalar-quantised copies
    of the vectors (``IndexRefine`` over ``IndexScalarQuantizer`` SQ8, FAISS's ``"PQ32x4fs,Refine(SQ8)"``): dim + 16
    bytes a reference, a quarter of the float32 vectors that ``pq_refine`` keeps (0.49 GiB per million at D 512).
  - ``ivfpq_disk``: ``ivfpq_refine``'s inverted lists of 4-bit fast-scan codes in memory (``m / 2`` bytes a
    reference and its 8-byte row number: 40 bytes at m=64), their best ``k_factor * k`` candidates re-ranked by
    exact inner products with the full descriptors, kept as float16 rows in files beside the index and read
    memory-mapped (half_vectors.py): a search needs the codes and the pages of the rows it re-ranks, not the
    2 x dim bytes a reference that the files hold.
  - ``hnsw``: a navigable small-world graph over the full vectors (``IndexHNSWFlat``; Malkov & Yashunin, TPAMI
    2018): ``hnsw_m`` links per node, ``ef_construction`` / ``ef_search`` candidates while building / searching.
  ``pq_refine``, ``ivfpq_refine`` and ``hnsw`` return exact inner products of the rows they return; ``pq_sq8``
  returns SQ8 estimates (within about 1e-3), ``ivfpq_disk`` those of the float16 rows (within about 1e-3),
  ``ivfpq`` PQ estimates.

Descriptors are L2-normalised, so the largest inner product is the smallest distance 2 - 2 a.b. What is added,
trained on or searched goes through `geoloc.eval.descriptors.unit_rows`, as in `recall_at_k`: rows off unit length
are normalised (cosine), NaN/inf rows raise FloatingPointError, all-zero rows ValueError, on both backends. Results
of either backend are ordered best first, the lower row first among equal scores (`geoloc.eval.candidates.ordered`).
A flat index gives back its stored vectors (`vectors`), so a saved gallery can be scored exactly.

Built in parts: `trained_empty` gives an index's trained, empty copy (the codebook every part is filled from), and
`merge` appends other parts' rows with FAISS's own ``merge_from`` (their codes are copied, nothing is re-encoded),
except the fast-scan IVF kinds', whose exact rows are added again (FAST_SCAN_IVF_KINDS: the same codes).
A FAISS index is saved with ``faiss.write_index`` into a file beside the record and read back memory-mapped
(``IO_FLAG_MMAP_IFC``), so neither saving nor loading copies it whole into memory.
"""
from __future__ import annotations

import io
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import torch

from geoloc.eval.candidates import ordered
from geoloc.eval.descriptors import as_float_tensor, unit_rows
from geoloc.eval.half_vectors import HalfVectors
from geoloc.eval.index_kinds import (BUILDERS, FAST_SCAN_IVF_KINDS, KINDS, PQ_KINDS, REFINE_KINDS, TRAIN_POINTS,
                                     IndexParams, import_faiss, positive_ints, set_search_knobs, sub_quantisers,
                                     training_points, training_rows)
from geoloc.eval.index_structure import check_structure
from geoloc.eval.scoring import SCORE_BUDGET, top_k

__all__ = ["GalleryIndex", "import_faiss"]

_FORMAT = "geoloc.gallery/1"
_ADD_BLOCK = 65536


class GalleryIndex:
    """Reference descriptors (N x dim) for top-k inner-product search.

    Args:
        dim: descriptor dimension.
        backend: ``"torch"`` (exact) or ``"faiss"``.
        kind: ``"flat"`` (exact) or, with FAISS, ``"ivfpq"``, ``"pq_refine"``, ``"ivfpq_refine"``, ``"pq_sq8"``,
            ``"ivfpq_disk"``, ``"hnsw"`` (module docstring).
        params: the FAISS kinds' knobs (IndexParams); `knobs` given by name replace single ones of them.
        device: torch backend only: where the gallery lives (default: where the first added descriptors are).
        chunk_size: queries per block of the torch search (`geoloc.eval.scoring`).
    """

    def __init__(self, dim: int, backend: str = "torch", kind: str = "flat", params: IndexParams | None = None,
                 device: str | torch.device | None = None, chunk_size: int = 1024, **knobs):
        if backend not in ("torch", "faiss"):
            raise ValueError(f"backend must be 'torch' or 'faiss', got {backend!r}")
        if kind not in KINDS or (backend == "torch" and kind != "flat"):
            raise ValueError(f"kind must be 'flat' (torch, faiss) or one of {KINDS[1:]} (faiss), got {kind!r} for "
                             f"{backend}")
        unknown = sorted(set(knobs) - {f.name for f in fields(IndexParams)})
        if unknown:
            raise TypeError(f"GalleryIndex has no knob {unknown}; its knobs are {[f.name for f in fields(IndexParams)]}")
        params = replace(params or IndexParams(), **knobs)
        if kind in PQ_KINDS and dim % sub_quantisers(kind, vars(params))[1]:
            knob, m = sub_quantisers(kind, vars(params))
            raise ValueError(f"{kind} needs {knob} (sub-quantisers) to divide dim, got dim={dim}, {knob}={m}")
        if kind == "ivfpq" and params.nbits > 16:
            raise ValueError(f"ivfpq needs nbits (bits per sub-code) in 1..16, got {params.nbits}")
        self.dim, self.backend, self.kind = int(dim), backend, kind
        self.params = {f.name: int(getattr(params, f.name)) for f in fields(IndexParams)}
        self.chunk_size = int(chunk_size)
        self._device = torch.device(device) if device is not None else None
        self._descriptors: torch.Tensor | None = None  # torch backend
        self._half = HalfVectors(self.dim) if kind == "ivfpq_disk" else None  # the rows ivfpq_disk re-ranks from
        if self.chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        self._index = None
        self._mapped = False  # a FAISS index memory-mapped read-only from its file (load): it cannot change
        if backend == "faiss":
            faiss = import_faiss()
            self._index = BUILDERS[kind](faiss, self.dim, self.params)
            set_search_knobs(faiss, kind, self._index, self.params)

    def set_search_params(self, **knobs) -> None:
        """Change search-time knobs (``nprobe``, ``k_factor``, ``ef_search``) of a built index."""
        unknown = set(knobs) - {"nprobe", "k_factor", "ef_search"}
        if unknown:
            raise ValueError(f"search knobs are nprobe, k_factor and ef_search, got {sorted(unknown)}")
        self.params.update(positive_ints(knobs, "search knobs"))
        if self.backend == "faiss":
            set_search_knobs(import_faiss(), self.kind, self._index, self.params)

    def __len__(self) -> int:
        if self.backend == "faiss":
            return int(self._index.ntotal)
        return 0 if self._descriptors is None else int(self._descriptors.shape[0])

    def _check(self, x, name: str) -> torch.Tensor:
        x = as_float_tensor(x, name)
        if x.shape[1] != self.dim:
            raise ValueError(f"{name} must have dimension {self.dim}, got {x.shape[1]}")
        return unit_rows(x, name)

    def train(self, descriptors, max_points: int = TRAIN_POINTS, seed: int = 0) -> None:
        """Train the IVF / PQ quantisers on (a seeded sample of at most ``max_points`` of: `training_rows`) the
        descriptors."""
        if self.backend != "faiss" or self._index.is_trained:
            return
        x = self._check(descriptors, "reference")
        needed, trains = training_points(self.kind, self.params)
        if x.shape[0] < needed:
            raise ValueError(f"the {self.kind} index trains {trains}, so it needs at least {needed} descriptors to "
                             f"train on, got {x.shape[0]}: use kind='flat' (exact, and fast at this size)")
        rows = training_rows(x.shape[0], max_points, seed)
        if rows is not None:
            x = x[rows]
        self._index.train(np.ascontiguousarray(x.cpu().numpy(), dtype=np.float32))

    def add(self, descriptors) -> "GalleryIndex":
        """Append N x dim descriptors; their row numbers continue from ``len(self)``. Trains IVF / PQ if needed."""
        x = self._check(descriptors, "reference")
        if self.backend == "faiss":
            self._writable("add to")
            if not self._index.is_trained:
                self.train(x)
            for s in range(0, x.shape[0], _ADD_BLOCK):  # IVF-PQ holds a residual per added row: add in blocks
                block = np.ascontiguousarray(x[s:s + _ADD_BLOCK].cpu().numpy(), dtype=np.float32)
                if self._half is not None:  # the codes of the rows as kept: a merge encodes them again alike
                    block = block.astype(np.float16).astype(np.float32)
                    self._half.append(block)
                self._index.add(block)
            return self
        if self._device is None:
            self._device = x.device
        x = x.to(self._device)
        # The first block is kept without a copy when it is already on the right device.
        self._descriptors = x if self._descriptors is None else torch.cat([self._descriptors, x.to(self._descriptors)])
        return self

    @property
    def is_trained(self) -> bool:
        """Whether the quantisers are trained (always, for the kinds that train nothing)."""
        return self.backend == "torch" or bool(self._index.is_trained)

    def trained_empty(self) -> "GalleryIndex":
        """A copy with the same trained quantisers (the codebook) and no rows: what each part of a gallery built
        in parts is filled from."""
        if not self.is_trained:
            raise ValueError(f"the {self.kind} index is not trained yet: train it (or add descriptors) first")
        self._writable("copy")  # FAISS's clone of a mapped index shares the mapping, and its reset aborts
        empty = GalleryIndex(self.dim, self.backend, self.kind, device=self._device, chunk_size=self.chunk_size,
                             **self.params)
        if self.backend == "faiss":
            faiss = import_faiss()
            empty._index = faiss.clone_index(self._index)
            empty._index.reset()
            set_search_knobs(faiss, self.kind, empty._index, self.params)
        return empty

    def merge(self, other: "GalleryIndex") -> "GalleryIndex":
        """Append `other`'s rows (their row numbers continue from ``len(self)``), moving their stored codes with
        FAISS's ``merge_from`` (the fast-scan IVF kinds: encoding their exact rows again), which leaves `other`
        empty: both must hold the same kind, built from the same codebook (`trained_empty`), and neither may be
        memory-mapped."""
        if (other.backend, other.kind, other.dim) != (self.backend, self.kind, self.dim):
            raise ValueError(f"cannot merge a {other.backend} {other.kind} index of dim {other.dim} into a "
                             f"{self.backend} {self.kind} index of dim {self.dim}")
        if len(other) == 0:
            return self
        if self.backend == "torch":
            return self.add(other._descriptors)
        self._writable("merge into")
        other._writable("merge (FAISS empties it) from")
        faiss = import_faiss()
        target, source = faiss.downcast_index(self._index), faiss.downcast_index(other._index)
        if self.kind in FAST_SCAN_IVF_KINDS:  # encoded again from the exact rows the other holds: see above
            for block in _blocks_of(other):
                self._index.add(block)
            source.reset()
        elif self.kind in REFINE_KINDS:  # IndexRefine has no merge_from: merge its two parts, then count the rows
            for part in ("base_index", "refine_index"):
                _merge_from(faiss, getattr(target, part), getattr(source, part))
            target.ntotal += source.ntotal
        else:
            _merge_from(faiss, target, source)
        if self._half is not None:
            self._half.extend(other._half)
        return self

    def _writable(self, what: str) -> None:
        if self._mapped:
            raise ValueError(f"cannot {what} a gallery index memory-mapped from its file: load it with "
                             "GalleryIndex.load(path, mmap=False)")

    def search(self, query, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Top-k references per query (Q x dim): (Q x k scores, Q x k row numbers), best first (the lower row
        first among equal scores), on the CPU. k is capped at ``len(self)``.
        """
        if len(self) == 0:
            raise ValueError("search on an empty gallery: add descriptors first")
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        q = self._check(query, "query")
        k = min(int(k), len(self))
        if self.backend == "torch":
            scores, rows = top_k(q, self._descriptors, k, chunk_size=self.chunk_size)
            return scores.float(), rows
        q = np.ascontiguousarray(q.cpu().numpy(), dtype=np.float32)
        if self.kind == "ivfpq_disk":
            return self._reranked(q, k)
        if self.kind == "flat":  # one call: the exact path of recall_at_k(backend="faiss")
            scores, idx = self._index.search(q, k)
            return ordered(torch.from_numpy(scores), torch.from_numpy(idx))
        # Queries per call: FAISS holds k (refine kinds: k_factor * k) candidates per query of a call.
        per_query = k * (self.params["k_factor"] if self.kind in REFINE_KINDS else 1)
        step = max(1, SCORE_BUDGET // per_query)
        blocks = [self._index.search(q[s:s + step], k) for s in range(0, q.shape[0], step)]
        return ordered(torch.from_numpy(np.concatenate([b[0] for b in blocks])),
                       torch.from_numpy(np.concatenate([b[1] for b in blocks])))

    def _reranked(self, q: np.ndarray, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """ivfpq_disk: the codes' best k_factor * k rows per query, scored again with the float16 rows, best k."""
        shortlist = min(k * self.params["k_factor"], len(self))
        scores, rows = [], []
        for s in range(0, q.shape[0], 256):  # 256 queries' shortlisted rows at a time
            _, candidates = self._index.search(q[s:s + 256], shortlist)
            found = candidates >= 0  # a query whose nprobe lists hold fewer rows than the shortlist
            vectors = self._half.gather(np.where(found, candidates, 0).ravel()).reshape(*candidates.shape, self.dim)
            exact = np.einsum("qd,qkd->qk", q[s:s + 256], vectors)
            scores.append(np.where(found, exact, -np.inf).astype(np.float32))
            rows.append(candidates)
        best_scores, best_rows = ordered(torch.from_numpy(np.concatenate(scores)),
                                         torch.from_numpy(np.concatenate(rows)))
        return best_scores[:, :k], best_rows[:, :k]

    def vectors(self) -> torch.Tensor:
        """N x dim: the stored descriptors of a flat (exact) index, as they were added (unit rows), where the
        index keeps them (the torch backend: its device; FAISS: the CPU)."""
        if self.kind != "flat":
            raise ValueError(f"a {self.kind} index keeps codes, not its vectors: only kind=flat gives them back")
        if len(self) == 0:
            raise ValueError("an empty gallery has no vectors: add descriptors first")
        if self.backend == "torch":
            return self._descriptors
        return torch.from_numpy(self._index.reconstruct_n(0, len(self)))

    def save(self, path: str | Path) -> None:
        """``torch.save`` of a plain dict at `path` for either backend; a FAISS index goes into a file beside it
        (`faiss_file`, ``faiss.write_index``, straight from the index). Reload with ``GalleryIndex.load``."""
        state = dict(format=_FORMAT, dim=self.dim, backend=self.backend, kind=self.kind, params=self.params,
                     chunk_size=self.chunk_size)
        path = Path(path)
        if self.backend == "faiss":
            faiss = import_faiss()
            blob = faiss_file(path)
            tmp_blob = blob.with_name(blob.name + ".tmp")
            faiss.write_index(self._index, str(tmp_blob))
            state.update(faiss_file=blob.name, faiss_bytes=tmp_blob.stat().st_size)
            tmp_blob.replace(blob)
            if self._half is not None:
                state["half_files"] = self._half.write(path.with_suffix(""))
        else:
            state["descriptors"] = None if self._descriptors is None else self._descriptors.cpu()
        tmp = path.with_name(path.name + ".tmp")
        torch.save(state, tmp)
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path, device: str | torch.device | None = None, mmap: bool = True) -> "GalleryIndex":
        """Load a saved gallery; the torch backend goes to ``device`` (default: the CPU). A FAISS index is
        memory-mapped read-only from its file where FAISS can (`mmap`; the codes of flat, PQ, SQ and refine
        indexes): pages are read as searches touch them, and such an index cannot grow (load with mmap=False to
        add or merge into it). A missing file raises FileNotFoundError; a truncated, corrupt or foreign one, or
        one whose FAISS parts disagree (index_structure.py: checked without reading the codes), ValueError naming
        the file."""
        path = Path(path)
        buf = io.BytesIO(path.read_bytes())
        try:
            state = torch.load(buf, weights_only=True)
        except Exception as err:  # torch's message (a page on a cut zip archive) names no file
            raise ValueError(f"could not read the gallery index {path}: it is truncated, corrupt or not a "
                             f"gallery.pt ({_first_line(err)})") from err
        if not isinstance(state, dict) or state.get("format") != _FORMAT:
            raise ValueError(f"{path} is not a geoloc gallery index (expected format {_FORMAT!r})")
        try:
            index = cls(state["dim"], state["backend"], state["kind"], device=device,
                        chunk_size=state["chunk_size"], **state["params"])
            if index.backend == "faiss":
                faiss = import_faiss()
                expected, index._index = index._index, _read_faiss(faiss, path, state, mmap)
                index._mapped = mmap and "faiss_file" in state
                blob = path.with_name(state.get("faiss_file", path.name))  # older records hold the index inside
                check_structure(faiss, index._index, expected, index.dim, blob)
                set_search_knobs(faiss, index.kind, index._index, index.params)
                if index._half is not None:
                    index._half = HalfVectors.open(path.parent, state["half_files"], index.dim)
                    if len(index._half) != len(index):
                        raise ValueError(f"its float16 rows count {len(index._half)} rows, its index {len(index)}")
            elif state["descriptors"] is not None:
                index.add(state["descriptors"])
        except ImportError:
            raise
        except Exception as err:  # a record without its keys, a FAISS blob cut inside the archive
            raise ValueError(f"the gallery index {path} is corrupt ({_first_line(err)})") from err
        return index


def _blocks_of(index: GalleryIndex):
    """The rows a fast-scan IVF index was encoded from, block by block as float32: ivfpq_disk's float16 rows,
    ivfpq_refine's refinement vectors."""
    if index._half is not None:
        yield from index._half.slices(_ADD_BLOCK)
        return
    refine = import_faiss().downcast_index(index._index).refine_index
    for s in range(0, len(index), _ADD_BLOCK):
        yield refine.reconstruct_n(s, min(_ADD_BLOCK, len(index) - s))


def _merge_from(faiss, target, source) -> None:
    """FAISS's merge_from: inverted lists store row ids (shifted by the rows already held), flat codes are stored
    in row order and take none."""
    target, source = faiss.downcast_index(target), faiss.downcast_index(source)
    target.merge_from(source, target.ntotal if isinstance(target, faiss.IndexIVF) else 0)


def faiss_file(path: Path) -> Path:
    """Where the FAISS index of the gallery index file `path` is written: beside it, `<stem>.faiss`."""
    return Path(path).with_suffix(".faiss")


def index_files(path: Path) -> list[Path]:
    """Every file `GalleryIndex.save(path)` may write: `path`, its FAISS index and an ivfpq_disk index's float16
    rows (`<stem>.<i>.f16`, half_vectors.py)."""
    path = Path(path)
    return [path, faiss_file(path), *sorted(path.parent.glob(f"{path.stem}.*.f16"))]


def _read_faiss(faiss, path: Path, state: dict, mmap: bool):
    if "faiss_index" in state:  # saved whole inside the record by earlier versions
        return faiss.deserialize_index(state["faiss_index"].numpy())
    blob = path.with_name(state["faiss_file"])
    if not blob.is_file():
        raise ValueError(f"its FAISS index {blob} is missing: the two files are written together")
    if blob.stat().st_size != state["faiss_bytes"]:
        raise ValueError(f"its FAISS index {blob} holds {blob.stat().st_size} bytes, {state['faiss_bytes']} "
                         f"were written: it is truncated or was replaced")
    flags = faiss.IO_FLAG_MMAP_IFC | faiss.IO_FLAG_READ_ONLY if mmap else 0
    return faiss.read_index(str(blob), flags)


def _first_line(err: Exception) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return f"{type(err).__name__}: {lines[0] if lines else ''}"
