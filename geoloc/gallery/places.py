"""What a saved gallery knows besides its descriptors: where each reference is, and the split's queries.

Written by `gallery.save=DIR` next to the index, read by localize.py and `geoloc serve`:
- DIR/references.jsonl: one line per gallery row: {"path": file under the dataset root, then "lat", "lon"
  (degrees) or "x_m", "y_m" (metres, e.g. CVACT's UTM) where the dataset has positions, and "extent_m": the
  [height, width] metres the tile covers where the dataset knows its scale (VIGOR, the synthetic layouts), which
  a refiner's answer inside the tile is measured by};
- DIR/queries.jsonl: one line per query of the split: {"path", its position, "positive": its true gallery row,
  "semi_positives": [rows]}, so a query image of the split is localized with its true position and metre error.
Paths are relative to the dataset root stored in gallery.json ("root", absolute, so a gallery built with a relative
`dataset.root` still finds its images from another folder). `read_places` checks every line (JSON, fields, rows in
range) and the count against gallery.json, naming the file and the line.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoloc.config import ConfigError
from geoloc.data.io import read_rgb
from geoloc.data.retrieval_split import RetrievalSplit

POSITION_KEYS = {"latlon": ("lat", "lon"), "xy": ("x_m", "y_m")}


def _rel(path: Path, root: Path) -> str:
    try:
        return Path(path).relative_to(root).as_posix()
    except ValueError:
        return str(path)


def rebased(path: str, root: str | Path, new_root: str | Path) -> str:
    """A references.jsonl path under `root` as a gallery whose root is `new_root` writes it: relative to
    `new_root` where the file lies under it, else absolute (an appended gallery's references from other roots)."""
    return _rel(Path(root) / path, Path(new_root))


def _position(kind: str | None, row) -> dict:
    return {} if kind is None or row is None else dict(zip(POSITION_KEYS[kind], map(float, row)))


def split_record(split: RetrievalSplit) -> dict:
    """What gallery.json records of the split a gallery was built from: its name, its absolute root and the sha256
    of its reference paths (relative to the root) in gallery-row order, so a reordered split of the same size is
    told apart."""
    digest = reference_paths_sha256(_rel(p, split.root) for p in split.references)
    return {"split": split.name, "root": str(Path(split.root).resolve()), "references_sha256": digest}


def reference_paths_sha256(paths) -> str:
    """sha256 of reference paths (relative to the root) in gallery-row order: what `references_sha256` records."""
    return hashlib.sha256("\n".join(paths).encode()).hexdigest()


def write_places(folder: Path, split: RetrievalSplit, rows=None) -> dict:
    """Write references.jsonl (of the references `rows`, default all: a gallery built in parts holds some) and
    queries.jsonl; returns the keys gallery.json records about them."""
    kind, query_pos, reference_pos = split.positions()
    extent = split.reference_extent_m
    refs = [json.dumps({"path": _rel(split.references[i], split.root),
                        **_position(kind, None if reference_pos is None else reference_pos[i]),
                        **({} if extent is None else {"extent_m": [float(v) for v in extent[i]]})})
            for i in (range(split.num_references) if rows is None else rows)]
    queries = []
    for i, p in enumerate(split.queries):
        semi = [] if split.semi_positives is None else [int(s) for s in split.semi_positives[i] if s >= 0]
        queries.append(json.dumps({"path": _rel(p, split.root),
                                   **_position(kind, None if query_pos is None else query_pos[i]),
                                   "positive": int(split.positives[i]), "semi_positives": semi}))
    for name, lines in (("references.jsonl", refs), ("queries.jsonl", queries)):
        # into the save's temporary folder (gallery_folder.py)
        (folder / name).write_text("".join(line + "\n" for line in lines))
    # tile_labels: the label set behind the queries' truth in their tiles (RetrievalSplit.tile_labels), or None
    return {**split_record(split), "positions": kind, "query_view": split.query_view, "tile_labels": split.tile_labels}


@dataclass
class Places:
    """The gallery's references and the split's queries, as written by `write_places`."""

    root: Path
    kind: str | None  # "latlon" | "xy" | None
    references: list[str]
    reference_positions: np.ndarray | None  # (N, 2)
    queries: dict[str, dict]  # query path (relative to root) -> its line
    reference_extent_m: np.ndarray | None = None  # (N, 2) metres (height, width) each tile covers, where known

    def reference(self, row: int) -> dict:
        """{"row", "path", position keys} of gallery row `row`."""
        out = {"row": int(row), "path": self.references[row]}
        if self.reference_positions is not None:
            out.update(_position(self.kind, self.reference_positions[row]))
        return out

    def tile_image(self, path: str) -> np.ndarray | None:
        """A reference's image file (`path` as `reference` gives it) as H×W×3 uint8 RGB, or None when it is not
        there (a gallery moved away from its images)."""
        try:
            return read_rgb(self.root / path)
        except (OSError, ValueError):
            return None

    def query_of(self, image: Path | None) -> dict | None:
        """The split's line for this image file, or None when it is not one of the split's queries."""
        if image is None:
            return None
        # a dataset folder of links (images linked in from elsewhere) names them by the link: look the image up
        # under its own path first, then with links followed
        plain = self.queries.get(_rel(Path(os.path.abspath(image)), Path(os.path.abspath(self.root))))
        return plain if plain is not None else self.queries.get(_rel(Path(image).resolve(), self.root.resolve()))

    def position_of(self, line: dict) -> np.ndarray | None:
        if self.kind is None or POSITION_KEYS[self.kind][0] not in line:
            return None
        return np.array([line[k] for k in POSITION_KEYS[self.kind]], np.float64)


def read_places(folder: Path, info: dict) -> Places:
    """The places of the gallery in `folder` (info = its gallery.json, checked: gallery_folder.py). A missing
    file raises FileNotFoundError; a cut line, a missing field, a row out of range or a count other than
    gallery.json's ConfigError naming the file (and the line)."""
    folder = Path(folder)
    missing = [n for n in ("references.jsonl", "queries.jsonl") if not (folder / n).is_file()]
    if missing or "root" not in info:
        raise FileNotFoundError(f"the gallery in {folder} lacks {', '.join(missing) or 'root in gallery.json'}: it "
                                "was saved by an older geoloc; rebuild it with `python evaluate.py ckpt=... "
                                f"gallery.save={folder}`")
    kind, rows = info.get("positions"), int(info["num_references"])
    if kind is not None and kind not in POSITION_KEYS:
        raise ConfigError(f"{folder / 'gallery.json'}: positions must be one of {sorted(POSITION_KEYS)} or null, "
                          f"got {kind!r}")
    wanted = POSITION_KEYS[kind] if kind is not None else ()
    refs = _json_lines(folder / "references.jsonl", lambda line: _check_reference(line, wanted))
    if len(refs) != rows:
        raise ConfigError(f"{folder / 'references.jsonl'} holds {len(refs)} references, but the gallery has {rows} "
                          "rows (gallery.json): the file was cut or edited, and gallery rows would name the wrong "
                          "tiles")
    positions = None
    if kind is not None:
        positions = np.array([[r[k] for k in POSITION_KEYS[kind]] for r in refs], np.float64)
    queries = {}
    for q in _json_lines(folder / "queries.jsonl", lambda line: _check_query(line, rows)):
        queries[q["path"]] = q
    extent = None
    if refs and all("extent_m" in r for r in refs):
        extent = np.array([r["extent_m"] for r in refs], np.float64)
    return Places(Path(info["root"]), kind, [r["path"] for r in refs], positions, queries, extent)


def _json_lines(path: Path, check) -> list[dict]:
    """Each non-empty line of a JSON-lines file as a dict; `check(line)` returns what is wrong with one, or ""."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path} is not UTF-8 text ({err.reason} at byte {err.start}): it is corrupt") from None
    records = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError as err:
            raise ConfigError(f"{path} line {number} is not JSON ({err.msg}, column {err.colno}): a line cut by an "
                              "interrupted write, or an edit") from None
        problem = "it is not an object" if not isinstance(record, dict) else check(record)
        if problem:
            raise ConfigError(f"{path} line {number}: {problem}")
        records.append(record)
    return records


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check_reference(line: dict, position_keys: tuple) -> str:
    if not isinstance(line.get("path"), str):
        return "no \"path\" (a string)"
    bad = [k for k in position_keys if not _finite(line.get(k))]
    extent = line.get("extent_m", [1.0, 1.0])
    if not (isinstance(extent, list) and len(extent) == 2 and all(_finite(v) and v > 0 for v in extent)):
        return f"\"extent_m\" must be [height, width] metres > 0, got {extent!r}"
    return f"no finite {', '.join(bad)}" if bad else ""


def _check_query(line: dict, rows: int) -> str:
    if not isinstance(line.get("path"), str):
        return "no \"path\" (a string)"
    semi = line.get("semi_positives", [])
    row = lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v < rows  # noqa: E731
    if not row(line.get("positive")):
        return f"\"positive\" must be a gallery row in 0..{rows - 1}, got {line.get('positive')!r}"
    if not isinstance(semi, list) or not all(map(row, semi)):
        return f"\"semi_positives\" must be a list of gallery rows in 0..{rows - 1}, got {semi!r}"
    bad = [k for keys in POSITION_KEYS.values() for k in keys if k in line and not _finite(line[k])]
    return f"{', '.join(bad)} not a finite number" if bad else ""
