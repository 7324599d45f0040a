"""The full descriptors of an `ivfpq_disk` gallery, kept as float16 rows on disk and read back memory-mapped.

An `ivfpq_disk` index holds 64-byte IVF-PQ codes in memory and re-ranks its candidates with their exact inner
products, read from these rows (search_index.py). The rows are a list of blocks: arrays in memory while an index is
built, files mapped read-only once it is saved or loaded. Each file is raw float16, row-major, with no header
(gallery.pt records each file's name and row count, and a file of another size is refused), so a search reads only
the pages of the rows it re-ranks.

Saved (`write`), the blocks held in memory go into one new file, and a block that is already a file (the shards
of a merge, a gallery appended to) is linked into the new folder, not copied: joining shards or appending to a
gallery costs no pass over the rows already written.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

DTYPE = np.float16
_SLICE = 65536  # rows a block is written a slice at a time


class HalfVectors:
    """N x dim float16 rows, appended block by block, gathered by row number as float32."""

    def __init__(self, dim: int, blocks: list[np.ndarray] | None = None):
        self.dim = int(dim)
        self._blocks: list[np.ndarray] = []
        self._ends = np.zeros(0, dtype=np.int64)
        for block in blocks or []:
            self._add_block(block)

    def __len__(self) -> int:
        return int(self._ends[-1]) if len(self._ends) else 0

    def append(self, rows: np.ndarray) -> None:
        """Add rows (n x dim, any float dtype); they are stored as float16."""
        if rows.ndim != 2 or rows.shape[1] != self.dim:
            raise ValueError(f"rows must be n x {self.dim}, got {tuple(rows.shape)}")
        self._add_block(np.ascontiguousarray(rows, dtype=DTYPE))

    def extend(self, other: "HalfVectors") -> None:
        """Add `other`'s rows after these ones, without copying them (a mapped block stays mapped)."""
        if other.dim != self.dim:
            raise ValueError(f"cannot join float16 rows of dim {other.dim} to rows of dim {self.dim}")
        for block in other._blocks:
            self._add_block(block)

    def _add_block(self, block: np.ndarray) -> None:
        if len(block):
            self._blocks.append(block)
            self._ends = np.append(self._ends, len(self) + len(block))

    def gather(self, rows: np.ndarray) -> np.ndarray:
        """float32 rows (len(rows) x dim) for row numbers in 0..N-1, read in ascending order (one pass over each
        mapped file) and returned in the order asked."""
        rows = np.asarray(rows, dtype=np.int64)
        if rows.size and (rows.min() < 0 or rows.max() >= len(self)):
            raise IndexError(f"row numbers must lie in 0..{len(self) - 1}")
        unique, back = np.unique(rows, return_inverse=True)
        out = np.empty((len(unique), self.dim), dtype=np.float32)
        block_of = np.searchsorted(self._ends, unique, side="right")
        for b in np.unique(block_of):
            picked = block_of == b
            start = int(self._ends[b - 1]) if b else 0
            out[picked] = self._blocks[b][unique[picked] - start]
        return out[back.reshape(-1)]

    def slices(self, size: int):
        """The rows in order, at most `size` at a time, as float32 (a mapped block read a slice at a time)."""
        for block in self._blocks:
            for s in range(0, len(block), size):
                yield np.asarray(block[s:s + size], dtype=np.float32)

    def write(self, stem: Path) -> list[list]:
        """Write the rows as files `<stem>.<i>.f16` beside `stem`, each through a temporary file renamed when it is
        whole; returns [[file name, rows], ...] in row order, which `open` takes back."""
        stem, files, pending = Path(stem), [], []

        def flush():
            if pending:
                path = _numbered(stem, len(files))
                _write_blocks(path, pending)
                files.append([path.name, sum(len(b) for b in pending)])
                pending.clear()

        for block in self._blocks:
            if _whole_file(block):
                flush()
                path = _numbered(stem, len(files))
                _link_or_copy(Path(block.filename), path)
                files.append([path.name, len(block)])
            else:
                pending.append(block)
        flush()
        return files

    @classmethod
    def open(cls, folder: Path, files: list[list], dim: int) -> "HalfVectors":
        """Map the files `write` listed, in `folder`; a missing file, or one of another size than its rows x dim
        float16, is refused naming it."""
        blocks = []
        for name, rows in files:
            path = Path(folder) / name
            if not path.is_file():
                raise ValueError(f"its float16 rows {path} are missing: the index files are written together")
            expected = int(rows) * dim * np.dtype(DTYPE).itemsize
            if path.stat().st_size != expected:
                raise ValueError(f"its float16 rows {path} hold {path.stat().st_size} bytes, {expected} were written "
                                 f"({rows} rows x {dim}): the file is truncated or was replaced")
            if rows:
                blocks.append(np.memmap(path, dtype=DTYPE, mode="r", shape=(int(rows), dim)))
        return cls(dim, blocks)


def _whole_file(block: np.ndarray) -> bool:
    """Whether `block` maps the whole of a file (as `open` maps them), which can then be linked, not rewritten."""
    return (isinstance(block, np.memmap) and bool(block.filename) and Path(block.filename).is_file()
            and Path(block.filename).stat().st_size == block.nbytes)


def _numbered(stem: Path, i: int) -> Path:
    return stem.with_name(f"{stem.name}.{i}.f16")


def _write_blocks(path: Path, blocks: list[np.ndarray]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        for block in blocks:
            for s in range(0, len(block), _SLICE):
                f.write(np.ascontiguousarray(block[s:s + _SLICE], dtype=DTYPE).tobytes())
        f.flush()
        os.fsync(f.fileno())
    tmp.replace(path)


def _link_or_copy(source: Path, path: Path) -> None:
    """A hard link to the rows already on disk (they are never written to again), or a copy across file
    systems."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    try:
        os.link(source, tmp)
    except OSError:
        shutil.copyfile(source, tmp)
    tmp.replace(path)
