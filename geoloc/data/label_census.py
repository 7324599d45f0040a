"""Class pixel fractions of a split's label maps (r_c of MMDIP eq. 1), stored with what they were computed from.

`class_fractions.json` holds ``classes``, ``fractions`` (6 decimals, as the synthetic generator has always written
them, so a recomputed file keeps earlier runs' numbers), ``pixels`` (the counts) and ``source``: the label format,
split, class map, number of label files and a SHA-256 over their relative paths, sizes and modification times. A
stored file is used only while its ``source`` matches the labels on disk; otherwise it is recomputed (and rewritten
when the folder is writable), so edited, added or removed label maps never leave stale class weights behind.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

log = logging.getLogger(__name__)

FILE_NAME = "class_fractions.json"


def fingerprint(files: Sequence[Path], root: Path) -> str:
    """SHA-256 of each file's path relative to `root`, size and mtime (ns), in order: cheap, a stat per file."""
    h = hashlib.sha256()
    for f in files:
        st = os.stat(f)
        h.update(f"{os.path.relpath(f, root)}\t{st.st_size}\t{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def count_classes(files: Sequence[Path], read: Callable[[int], np.ndarray], num_classes: int) -> np.ndarray:
    """Pixels per class over the label maps ``read(i)`` of ``files[i]``; an id outside the class set names the file."""
    counts = np.zeros(num_classes, np.int64)
    for i, path in enumerate(files):
        lab = np.asarray(read(i))
        if lab.size and (lab.min() < 0 or lab.max() >= num_classes):
            bad = np.unique(lab[(lab < 0) | (lab >= num_classes)])[:5].tolist()
            raise ValueError(f"{path}: label values {bad} lie outside the class set 0..{num_classes - 1}")
        counts += np.bincount(lab.ravel(), minlength=num_classes)[:num_classes]
    if counts.sum() == 0:
        raise ValueError(f"no labelled pixels in the {len(files)} label files (first: {files[0] if files else None})")
    return counts


def _stale_reason(stored: dict | None, classes: Sequence[str], source: dict) -> str | None:
    if stored is None:
        return "not found"
    if not isinstance(stored, dict) or "source" not in stored:
        return "records no source (written before geoloc tracked what it was computed from)"
    if list(stored.get("classes", [])) != list(classes) or len(stored.get("fractions", [])) != len(classes):
        return f"was computed for other classes {stored.get('classes')}"
    old = stored["source"]
    changed = [k for k in source if old.get(k) != source[k]]
    if changed == ["fingerprint"]:
        return "its label files changed since (sizes or modification times)"
    if changed:
        return "was computed from other labels: " + ", ".join(f"{k} {old.get(k)!r} -> {source[k]!r}" for k in changed)
    return None


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as err:
        log.warning("%s is unreadable (%s): recomputing it", path, err)
        return {}


def stored_or_counted(path: Path, files: Sequence[Path], read: Callable[[int], np.ndarray], classes: Sequence[str],
                      source: dict, force: bool = False) -> list[float]:
    """The fractions stored at `path` if they were computed from exactly these label files; else counted anew.

    `source` describes the labels (format, split, class map, ...); the file count and fingerprint are added here.
    """
    source = {**source, "files": len(files), "fingerprint": fingerprint(files, path.parent)}
    stored = _read(path)
    reason = "recomputation asked for" if force else _stale_reason(stored, classes, source)
    if reason is None:
        return [float(f) for f in stored["fractions"]]
    counts = count_classes(files, read, len(classes))
    fractions = [round(float(c), 6) for c in counts / counts.sum()]
    record = {"classes": list(classes), "fractions": fractions, "pixels": counts.tolist(), "source": source}
    try:
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(record, indent=1) + "\n")
        os.replace(tmp, path)
        # a first count is routine; a stale file means the labels changed under it, which the user should see
        level = logging.INFO if force or stored is None else logging.WARNING
        log.log(level, "%s %s: recomputed from %d label files", path, reason, len(files))
    except OSError as err:
        log.warning("%s %s; recomputed from %d label files but could not store it (%s), so every start recounts",
                    path, reason, len(files), err)
    return fractions
