"""What a saved gallery knows besides its descriptors: where each reference is, and the split's queries.

Written by `gallery.save=DIR` next to the index, read by localize.py and `geoloc serve`:
- DIR/references.jsonl: one line per gallery row: {"path": file under the dataset root, then "lat", "lon"
  (degrees) or "x_m", "y_m" (metres, e.g. CVACT's UTM) where the dataset has positions};
- DIR/queries.jsonl: one line per query of the split: {"path", its position, "positive": its true gallery row,
  "semi_positives": [rows]}, so a query image of the split is localized with its true position and metre error.
Paths are relative to the dataset root stored in gallery.json ("root").
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoloc.data.retrieval_split import RetrievalSplit

POSITION_KEYS = {"latlon": ("lat", "lon"), "xy": ("x_m", "y_m")}


def _rel(path: Path, root: Path) -> str:
    try:
        return Path(path).relative_to(root).as_posix()
    except ValueError:
        return str(path)


def _position(kind: str | None, row) -> dict:
    return {} if kind is None or row is None else dict(zip(POSITION_KEYS[kind], map(float, row)))


def write_places(folder: Path, split: RetrievalSplit) -> dict:
    """Write references.jsonl and queries.jsonl; returns the keys gallery.json records about them."""
    kind, query_pos, reference_pos = split.positions()
    refs = [json.dumps({"path": _rel(p, split.root), **_position(kind, None if reference_pos is None else
                                                                  reference_pos[i])})
            for i, p in enumerate(split.references)]
    queries = []
    for i, p in enumerate(split.queries):
        semi = [] if split.semi_positives is None else [int(s) for s in split.semi_positives[i] if s >= 0]
        queries.append(json.dumps({"path": _rel(p, split.root),
                                   **_position(kind, None if query_pos is None else query_pos[i]),
                                   "positive": int(split.positives[i]), "semi_positives": semi}))
    for name, lines in (("references.jsonl", refs), ("queries.jsonl", queries)):
        tmp = folder / (name + ".tmp")
        tmp.write_text("\n".join(lines) + "\n")
        tmp.replace(folder / name)
    return {"root": str(split.root), "positions": kind, "query_view": split.query_view, "split": split.name}


@dataclass
class Places:
    """The gallery's references and the split's queries, as written by `write_places`."""

    root: Path
    kind: str | None  # "latlon" | "xy" | None
    references: list[str]
    reference_positions: np.ndarray | None  # (N, 2)
    queries: dict[str, dict]  # query path (relative to root) -> its line

    def reference(self, row: int) -> dict:
        """{"row", "path", position keys} of gallery row `row`."""
        out = {"row": int(row), "path": self.references[row]}
        if self.reference_positions is not None:
            out.update(_position(self.kind, self.reference_positions[row]))
        return out

    def query_of(self, image: Path | None) -> dict | None:
        """The split's line for this image file, or None when it is not one of the split's queries."""
        if image is None:
            return None
        return self.queries.get(_rel(Path(image).resolve(), self.root.resolve()))

    def position_of(self, line: dict) -> np.ndarray | None:
        if self.kind is None or POSITION_KEYS[self.kind][0] not in line:
            return None
        return np.array([line[k] for k in POSITION_KEYS[self.kind]], np.float64)


def read_places(folder: Path, info: dict) -> Places:
    """The places of the gallery in `folder` (info = its gallery.json)."""
    folder = Path(folder)
    missing = [n for n in ("references.jsonl", "queries.jsonl") if not (folder / n).is_file()]
    if missing or "root" not in info:
        raise FileNotFoundError(f"the gallery in {folder} lacks {', '.join(missing) or 'root in gallery.json'}: it "
                                "was saved by an older geoloc; rebuild it with `python evaluate.py ckpt=... "
                                f"gallery.save={folder}`")
    kind = info.get("positions")
    refs = [json.loads(line) for line in (folder / "references.jsonl").read_text().splitlines() if line]
    positions = None
    if kind is not None:
        positions = np.array([[r[k] for k in POSITION_KEYS[kind]] for r in refs], np.float64)
    queries = {}
    for line in (folder / "queries.jsonl").read_text().splitlines():
        if line:
            q = json.loads(line)
            queries[q["path"]] = q
    return Places(Path(info["root"]), kind, [r["path"] for r in refs], positions, queries)
