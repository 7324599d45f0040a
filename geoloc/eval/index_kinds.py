"""The FAISS kinds a gallery index can be: their names, how each is built empty, its knobs (IndexParams) and
their checks, what its quantisers train on. geoloc/eval/search_index.py describes each kind and holds the index
itself (GalleryIndex), which builds its FAISS index from here.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

TRAIN_POINTS = 200_000  # the most vectors the quantisers train on (a seeded sample of them)
KINDS = ("flat", "ivfpq", "pq_refine", "ivfpq_refine", "pq_sq8", "ivfpq_disk", "hnsw")
PQ_KINDS = ("ivfpq", "pq_refine", "ivfpq_refine", "pq_sq8", "ivfpq_disk")  # their sub-quantisers must divide dim
IVF_KINDS = ("ivfpq", "ivfpq_refine", "ivfpq_disk")  # inverted lists: nlist trained, nprobe searched
# Their inverted lists hold 4-bit codes in blocks of 32 rows. FAISS 1.15's merge_from corrupts the heap joining such
# lists of 1M rows (D 512, m 64: an abort in malloc), so a merge adds the other's exact rows again instead; the
# codes are the same, as the codebook encodes the same vectors (ivfpq_disk: its float16 rows, which `add` encodes).
FAST_SCAN_IVF_KINDS = ("ivfpq_refine", "ivfpq_disk")
REFINE_KINDS = ("pq_refine", "ivfpq_refine", "pq_sq8")  # IndexRefine: k_factor * k candidates re-ranked


def import_faiss():
    try:
        import faiss
    except ImportError as e:
        raise ImportError("the faiss backend needs faiss: pip install 'geoloc[faiss]' (or faiss-cpu)") from e
    return faiss


# One builder per kind: (faiss, dim, params) -> an empty FAISS index. FAISS's Python constructors keep a reference to
# the sub-index they wrap (coarse quantiser, PQ base), so it lives as long as the index.
def _flat(faiss, dim, p):
    return faiss.IndexFlatIP(dim)


def _ivfpq(faiss, dim, p):
    return faiss.IndexIVFPQ(faiss.IndexFlatIP(dim), dim, p["nlist"], p["m"], p["nbits"], faiss.METRIC_INNER_PRODUCT)


def _pq_refine(faiss, dim, p):
    # 4-bit codes: the fast-scan kernels keep the 16-entry look-up tables in SIMD registers.
    return faiss.IndexRefineFlat(faiss.IndexPQFastScan(dim, p["m"], 4, faiss.METRIC_INNER_PRODUCT))


def _ivf_fast_scan(faiss, dim, p):
    return faiss.IndexIVFPQFastScan(faiss.IndexFlatIP(dim), dim, p["nlist"], p["m"], 4, faiss.METRIC_INNER_PRODUCT)


def _ivfpq_refine(faiss, dim, p):
    return faiss.IndexRefineFlat(_ivf_fast_scan(faiss, dim, p))


def _pq_sq8(faiss, dim, p):
    return faiss.index_factory(dim, f"PQ{p['coarse_m']}x4fs,Refine(SQ8)", faiss.METRIC_INNER_PRODUCT)


def _hnsw(faiss, dim, p):
    index = faiss.IndexHNSWFlat(dim, p["hnsw_m"], faiss.METRIC_INNER_PRODUCT)
    index.hnsw.efConstruction = p["ef_construction"]  # a build knob: set before the first add
    return index


BUILDERS = {"flat": _flat, "ivfpq": _ivfpq, "pq_refine": _pq_refine, "ivfpq_refine": _ivfpq_refine,
             "pq_sq8": _pq_sq8, "ivfpq_disk": _ivf_fast_scan, "hnsw": _hnsw}  # ivfpq_disk: + float16 rows


def sub_quantisers(kind: str, params: dict) -> tuple[str, int]:
    """(the knob, its value) of a PQ kind's sub-quantisers, which must divide the descriptor dim."""
    return ("coarse_m", params["coarse_m"]) if kind == "pq_sq8" else ("m", params["m"])


def set_search_knobs(faiss, kind: str, index, p: dict) -> None:
    """Set the search-time knobs from ``params``, which is what gallery.json records, so the two always agree."""
    if kind in REFINE_KINDS:
        index = faiss.downcast_index(index)
        index.k_factor = float(p["k_factor"])
        index = faiss.downcast_index(index.base_index)
    if kind in IVF_KINDS:
        index.nprobe = p["nprobe"]
    if kind == "hnsw":
        faiss.downcast_index(index).hnsw.efSearch = p["ef_search"]


def training_points(kind: str, params: dict) -> tuple[int, str]:
    """(the fewest vectors a kind's quantisers train on, what they train): FAISS's k-means refuses fewer points
    than centroids. IVF kinds train ``nlist`` coarse centroids; PQ kinds 2^bits centroids per sub-quantiser (8 bits
    for ivfpq by default, 4 for the fast-scan kinds)."""
    parts = []
    if kind in IVF_KINDS:
        parts.append((params["nlist"], f"{params['nlist']} inverted lists (nlist)"))
    if kind in PQ_KINDS:
        bits = params["nbits"] if kind == "ivfpq" else 4  # the fast-scan kinds' codes are 4-bit
        parts.append((2 ** bits, f"{2 ** bits} centroids per sub-quantiser ({bits}-bit codes)"))
    if not parts:
        return 0, "nothing"
    return max(n for n, _ in parts), " and ".join(what for _, what in parts)


def training_rows(num: int, max_points: int = TRAIN_POINTS, seed: int = 0) -> torch.Tensor | None:
    """The rows of `num` references that the quantisers train on, in the order they are given to k-means: a
    seeded sample of `max_points` of them, or None (all of them, in order) when there are no more than that. A
    codebook trained from these rows of a split alone equals the one a whole gallery of it trains."""
    if num <= max_points:
        return None
    return torch.randperm(num, generator=torch.Generator().manual_seed(seed))[:max_points]


def is_count(value) -> bool:
    """An integer >= 1 (numpy's included; a bool is not one)."""
    return not isinstance(value, bool) and isinstance(value, (int, np.integer)) and value >= 1


def positive_ints(values: dict, what: str) -> dict:
    bad = [f"{key}={value!r}" for key, value in values.items() if not is_count(value)]
    if bad:
        raise ValueError(f"{what} must be integers >= 1, got {', '.join(bad)}")
    return {key: int(value) for key, value in values.items()}


@dataclass
class IndexParams:
    """The knobs of the FAISS kinds, each with its one default (gallery.* in evaluate.py extends these)."""

    nlist: int = 1024  # IVF kinds: inverted lists (capped at N / 39, FAISS's minimum training points per list)
    m: int = 64  # PQ kinds: sub-quantisers; must divide the descriptor dim
    nbits: int = 8  # ivfpq: bits per sub-code (the refine kinds and ivfpq_disk use 4-bit fast-scan codes)
    nprobe: int = 256  # IVF kinds: lists visited per query (of nlist 1,024 at 1M references, 256 kept 98.4% of the
    # exact R@1 with ivfpq_refine and ivfpq_disk; benchmarks/README.md)
    k_factor: int = 16  # refine kinds, ivfpq_disk: k_factor * k PQ candidates re-ranked (pq_sq8: from their SQ8
    # codes, ivfpq_disk: from their float16 rows on disk)
    coarse_m: int = 32  # pq_sq8: 4-bit sub-quantisers of the coarse code (coarse_m / 2 bytes a reference)
    hnsw_m: int = 32  # hnsw: links per node
    ef_construction: int = 40  # hnsw: candidate list while building
    ef_search: int = 256  # hnsw: candidate list while searching (128 kept 92% of the exact R@1 at 1M, 256 97.5%)

    def __post_init__(self):
        bad = [f"gallery.{f.name}={getattr(self, f.name)!r}" for f in fields(IndexParams)
               if not is_count(getattr(self, f.name))]
        if bad:
            raise ValueError(f"{', '.join(bad)}: the index knobs must be integers >= 1")
