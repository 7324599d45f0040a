"""A FAISS index read from a file, checked by its own structure before it is searched.

A gallery's index file may hold a FAISS index whose parts disagree: an outer IndexRefine counting other rows than
the PQ codes or the refine copies it wraps, an IVF whose inverted lists hold other rows than it counts, or a file
of another kind than its record names. FAISS opens such a file and then fails on every search (or, for coarse
codes shorter than the refine copies, never returns the rows past their end); an HNSW graph over another storage
FAISS refuses itself. The structure says so without reading the codes: the classes of the outer index and of each
part it wraps, their metric and dimension, and their row counts, so a multi-GiB index memory-mapped from its file
is checked in microseconds.
"""

from __future__ import annotations

from pathlib import Path


def index_parts(faiss, index) -> dict:
    """{name: the FAISS index} of `index` (downcast) and of each index it wraps: "outer", "base_index" and
    "refine_index" (IndexRefine), "storage" (HNSW)."""
    outer = faiss.downcast_index(index)
    parts = {"outer": outer}
    for name in ("base_index", "refine_index", "storage"):
        if getattr(outer, name, None) is not None:
            parts[name] = faiss.downcast_index(getattr(outer, name))
    return parts


def check_structure(faiss, index, expected, dim: int, where: Path) -> None:
    """Refuse `index` (read from the file `where`) unless its structure is that of `expected` (an empty index of
    the kind its record names) with `dim` dimensions: the same classes, every part of dimension `dim`, and every
    count of rows equal to the outer index's. A ValueError names the file and the part that disagrees."""
    parts, built = index_parts(faiss, index), index_parts(faiss, expected)
    shape = {name: type(part).__name__ for name, part in parts.items()}
    expect = {name: type(part).__name__ for name, part in built.items()}
    # a part FAISS reads back as a subclass of the one built is the same (IndexFlat with the inner product is read
    # as IndexFlatIP)
    if set(parts) != set(built) or any(not isinstance(parts[name], type(built[name]))
                                       or parts[name].metric_type != built[name].metric_type for name in parts):
        raise ValueError(f"{where} holds a FAISS index of parts {shape}, where its record's kind has {expect}: "
                         "the file was replaced by another gallery's")
    rows = int(parts["outer"].ntotal)
    problems = [f"{name} has dimension {part.d}" for name, part in parts.items() if part.d != dim]
    problems += [f"{name} holds {part.ntotal} rows" for name, part in parts.items() if part.ntotal != rows]
    for name, part in parts.items():
        if isinstance(part, faiss.IndexIVF) and part.invlists.compute_ntotal() != rows:
            problems.append(f"{name}'s inverted lists hold {part.invlists.compute_ntotal()} rows")
    if problems:
        raise ValueError(f"{where} holds a FAISS index whose parts disagree: its record gives dimension {dim} and the "
                         f"outer index holds {rows} rows, but {'; '.join(problems)}. Every search of it would fail "
                         "or miss rows: the file was edited or written from parts of other indexes")
