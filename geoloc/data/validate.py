"""Start-up check that every file a split names exists and fully decodes, so a run fails in seconds, not hours.

libjpeg decodes a truncated JPEG by filling the missing part with grey and only prints "Premature end of JPEG
file", with no file name. So completeness is checked on the bytes, before decoding:
- a JPEG must end with its end-of-image marker FF D9, and the first FF D9 after the first scan must be that one
  (an earlier one is libjpeg's "premature end of data segment": the rest of the image is lost);
- a PNG must end with its IEND chunk;
- an empty file, or one that is neither a JPEG, a PNG nor anything OpenCV decodes, is named as such.
Then the whole image is decoded at full size, strictly (`decode_rgb`: libjpeg-turbo in strict mode for JPEGs, OpenCV
otherwise; both release the GIL, so a thread pool runs decodes in parallel).

Training reads (`decode_rgb` with `min_size`) may decode a JPEG at 1/2, 1/4 or 1/8 scale (libjpeg's DCT scaling,
which skips most of the inverse DCT and colour conversion) when the transforms resize it to no more than that; the
same byte checks and the same strict decoder run on every read, so a reduced decode refuses what a full one does.

Files that passed are remembered by (size, mtime) in `$GEOLOC_CACHE/checked/<hash of root + split>.json`
(default `~/.cache/geoloc/checked/`), never inside the dataset root, which may be read-only: a second start only
stats the files. At training time `require_complete` checks the cheap part (the tail bytes) on every read.
"""

from __future__ import annotations

import hashlib
import json
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import simplejpeg

JPEG_SOI, JPEG_EOI = b"\xff\xd8", b"\xff\xd9"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # zero length, type, CRC: the last 12 bytes of every PNG
_PADDING = b"\x00\r\n\t "  # what some writers append after the end marker; not image data
_TAIL_BYTES = 64
_CACHE_VERSION = 1


class DatasetFileError(RuntimeError):
    pass


def _strip_padding(data: bytes) -> bytes:
    return data.rstrip(_PADDING)


def _jpeg_scan_start(data: bytes) -> int | None:
    """Offset just past the first start-of-scan header, walking the marker segments; None if they are broken."""
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            pos += 2
            continue
        length = int.from_bytes(data[pos + 2:pos + 4], "big")
        if length < 2:
            return None
        pos += 2 + length
        if marker == 0xDA:
            return pos if pos <= len(data) else None
    return None


def completeness_problem(head: bytes, tail: bytes, size: int) -> str | None:
    """What is wrong with a file from its first 8 and last few bytes alone (None: nothing seen)."""
    if size == 0:
        return "zero bytes (an empty file)"
    tail = _strip_padding(tail)
    if head.startswith(JPEG_SOI):
        if not tail.endswith(JPEG_EOI):
            return ("truncated JPEG: premature end, no end-of-image marker FF D9 at the end (a partial download? "
                    "libjpeg would fill the rest with grey)")
    elif head.startswith(PNG_SIGNATURE):
        if not tail.endswith(PNG_IEND):
            return "truncated PNG: no IEND chunk at the end (a partial download?)"
    return None


def content_problem(data: bytes) -> str | None:
    """The full-file checks on bytes in memory: completeness, then a JPEG's first end marker is its last."""
    problem = completeness_problem(data[:8], data[-_TAIL_BYTES:], len(data))
    if problem or not data.startswith(JPEG_SOI):
        return problem
    scan, end = _jpeg_scan_start(data), len(_strip_padding(data)) - 2
    if scan is None or scan > end:
        return "corrupt JPEG: its marker segments are broken before the image data"
    # Inside the compressed data every FF byte is followed by 00 or a restart marker, so an FF D9 there is an end.
    first_end = data.find(JPEG_EOI, scan)
    if first_end != end:
        return (f"premature end of JPEG data: an end-of-image marker at byte {first_end} of {len(data)}, so the "
                "rest of the image is lost (corrupt data, or other data appended after the image)")
    return None


def jpeg_reduction(height: int, width: int, min_size: tuple[int, int] | None) -> int:
    """The largest of 8, 4, 2 (else 1) by which libjpeg may scale an H×W JPEG down so that it stays at least
    `min_size` (H, W): its scaled side is ceil(side / factor), so the transforms never upsample more than at full
    size."""
    if min_size is None:
        return 1
    return next((f for f in (8, 4, 2) if -(-height // f) >= min_size[0] and -(-width // f) >= min_size[1]), 1)


def _decoded(data: bytes, min_size: tuple[int, int] | None = None) -> tuple[np.ndarray | None, str | None]:
    """(H×W×3 uint8 RGB, None) for complete image bytes, else (None, what is wrong). JPEGs are decoded by
    libjpeg-turbo in strict mode (simplejpeg), which refuses what libjpeg otherwise only warns about and fills
    with grey: a scan cut short with an end marker appended, or a header that promises more pixels than the data
    holds. Other formats go through OpenCV, whose PNG reader refuses a short or corrupt image stream.

    min_size: (H, W) a JPEG may be decoded down to (`jpeg_reduction`); other formats are decoded at full size."""
    problem = content_problem(data)
    if problem:
        return None, problem
    if data.startswith(JPEG_SOI):
        try:
            scale = {}
            if min_size is not None:
                height, width = simplejpeg.decode_jpeg_header(data)[:2]
                factor = jpeg_reduction(height, width, min_size)
                if factor > 1:  # the smallest scale libjpeg offers that keeps ceil(side / factor): 1/factor itself
                    scale = {"min_height": -(-height // factor), "min_width": -(-width // factor)}
            return simplejpeg.decode_jpeg(data, colorspace="RGB", strict=True, **scale), None
        except ValueError as err:
            return None, f"corrupt JPEG: {err} (libjpeg would fill the rest of the image with grey)"
    try:
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    except cv2.error:
        bgr = None
    if bgr is None or bgr.size == 0:
        if data.startswith(PNG_SIGNATURE):
            return None, "corrupt image: does not decode"
        return None, f"not an image: does not decode, and it starts with {data[:16]!r}"
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), None


REFETCH = "Re-download or re-extract it (the start-up check dataset.check_files=decode lists every such file)."


def decode_rgb(data: bytes, name: str | Path, fix: str = REFETCH,
               min_size: tuple[int, int] | None = None) -> np.ndarray:
    """Image bytes as H×W×3 uint8 RGB, complete or refused: DatasetFileError naming `name`, what is wrong and
    `fix`, what to do (a dataset file's by default). min_size: the (H, W) a JPEG may be decoded down to, by a
    factor of 2, 4 or 8 (`jpeg_reduction`); None: full size."""
    image, problem = _decoded(data, min_size)
    if problem:
        raise DatasetFileError(f"{name}: {problem}. {fix}")
    return image


def image_problem(path: Path) -> str | None:
    """Why `path` is not a complete, decodable image, or None."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return "missing"
    except OSError as err:
        return f"unreadable ({err.strerror or err})"
    return _decoded(data)[1]


def require_complete(path: str | Path) -> None:
    """Raise DatasetFileError naming `path` if its tail shows a truncated JPEG/PNG or it is empty (reads 72 bytes)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(8)
            size = f.seek(0, os.SEEK_END)
            f.seek(max(0, size - _TAIL_BYTES))
            tail = f.read()
    except OSError:
        return  # missing or unreadable: the decoder's own error names the file
    problem = completeness_problem(head, tail, size)
    if problem:
        raise DatasetFileError(f"{path}: {problem}. {REFETCH}")


# ---- the cache of checked files ---------------------------------------------------------------------------------
def checked_dir() -> Path:
    return Path(os.environ.get("GEOLOC_CACHE", Path.home() / ".cache" / "geoloc")) / "checked"


def cache_file(root: str | Path, split: str, kind: str) -> Path:
    """Where the files of (root, split) that passed check `kind` are remembered."""
    key = hashlib.sha1(f"{Path(root).resolve()}\n{split}\n{kind}".encode()).hexdigest()[:16]
    return checked_dir() / f"{key}.json"


def _load_cache(path: Path, kind: str) -> dict[str, list[int]]:
    try:
        found = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    ok = isinstance(found, dict) and found.get("version") == _CACHE_VERSION and found.get("kind") == kind
    return found.get("files", {}) if ok else {}


def _save_cache(path: Path, root, split: str, kind: str, files: dict[str, list[int]]) -> None:
    try:  # best effort: an unwritable cache only means the next start checks again
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps({"version": _CACHE_VERSION, "kind": kind, "root": str(root), "split": split,
                                   "files": files}))
        os.replace(tmp, path)
    except OSError:
        pass


def _report(problems: list[str], total: int, root, split: str, what: str, show: int) -> None:
    if problems:
        listed = "\n  ".join(problems[:show])
        raise DatasetFileError(
            f"{len(problems)} of {total} files of split '{split}' under root {root} are {what}:\n"
            f"  {listed}\nFix or re-extract the dataset, or point dataset.root at the right folder.")


def _stamp(path: Path) -> list[int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns]


def run_checks(paths: list[Path], root, split: str, kind: str, problem: Callable[[Path], str | None],
               show: int = 5, what: str = "missing or broken", workers: int | None = None) -> None:
    """Run `problem` on every file not remembered as passed since its last change; raise naming the failures.

    `kind` names the check in the cache, so files that passed one check are not taken as passing another.
    `workers` threads (default: one per CPU, at most 8) run the checks.
    """
    cache_path = cache_file(root, split, kind)
    passed = _load_cache(cache_path, kind)
    paths = [Path(p) for p in paths]
    stamps = {str(p): _stamp(p) for p in paths}
    todo = [p for p in paths if stamps[str(p)] is None or passed.get(str(p)) != stamps[str(p)]]
    with ThreadPoolExecutor(max_workers=workers or min(8, os.cpu_count() or 1)) as pool:
        found = list(pool.map(problem, todo))
    newly = {str(p): stamps[str(p)] for p, why in zip(todo, found) if not why and stamps[str(p)] is not None}
    if newly:
        _save_cache(cache_path, root, split, kind, {**passed, **newly})
    _report([f"{p} ({why})" for p, why in zip(todo, found) if why], len(paths), root, split, what, show)


def _exists_problem(path: str | Path) -> str | None:
    return None if Path(path).is_file() else "missing"


def check_files(paths: list[Path], root: str | Path, split: str, mode: str = "decode", show: int = 5,
                workers: int | None = None) -> None:
    """mode: "decode" (exists, complete, decodes at full size), "exists", or "off".

    Raises DatasetFileError counting the failures and naming the first `show`, each with its reason.
    """
    if mode == "off":
        return
    if mode == "decode":
        run_checks(paths, root, split, "decode", image_problem, show, workers=workers)
    elif mode == "exists":
        with ThreadPoolExecutor(max_workers=8) as pool:
            found = list(pool.map(_exists_problem, paths))
        _report([f"{p} ({why})" for p, why in zip(paths, found) if why], len(paths), root, split, "missing", show)
    else:
        raise ValueError(f"dataset.check_files must be 'decode', 'exists' or 'off', got {mode!r}")
