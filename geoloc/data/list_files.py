"""Reading a dataset's text lists (split files, satellite lists, csv tables): numbered lines, each entry once.

A byte-order mark is not part of the first entry: editors on Windows write one, and a name carrying it prints
like the right one but names no file. A name listed twice would be scored twice (VIGOR's duplicated split lines
count their queries twice and move the hit rate), so a repeat is refused naming both lines.
"""

from __future__ import annotations

import codecs
import csv
from collections.abc import Iterable
from pathlib import Path


def list_lines(path: str | Path, what: str) -> list[tuple[int, str]]:
    """(line number, text without surrounding white space) of each non-blank line of `path`, a `what` (e.g. "VIGOR
    split file"). UTF-8 with or without its byte-order mark, or UTF-16 with its mark; other bytes are refused,
    naming the file."""
    path = Path(path)
    return text_lines(path.read_bytes(), f"{what} {path}")


def text_lines(data: bytes, named: str) -> list[tuple[int, str]]:
    """list_lines of bytes that came from elsewhere (an upload), `named` in the refusal (e.g. "the upload 'a.csv'")."""
    encoding = "utf-16" if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)) else "utf-8-sig"
    try:
        text = data.decode(encoding)
    except UnicodeDecodeError as err:
        raise ValueError(f"{named} is not UTF-8 text ({err}); save it as UTF-8 or restore it from the "
                         "dataset release") from None
    return [(k, line.strip()) for k, line in enumerate(text.splitlines(), 1) if line.strip()]


def csv_rows(path: str | Path, what: str) -> list[tuple[int, list[str]]]:
    """(line number, fields) of each non-blank line of a csv file whose records are one line each."""
    return csv_lines(list_lines(path, what), path)


def csv_lines(lines: list[tuple[int, str]], named) -> list[tuple[int, list[str]]]:
    """(line number, fields) of (line number, text) lines, one csv record each; `named` in the refusal."""
    rows = []
    for k, line in lines:
        try:
            rows.append((k, next(csv.reader([line]))))
        except csv.Error as err:
            raise ValueError(f"{named}:{k}: not a csv row ({err}): {line[:120]!r}") from None
    return rows


def refuse_repeats(path: str | Path, keyed: Iterable[tuple[str, int]], what: str) -> None:
    """Each key once: `keyed` holds (key, line number) pairs, e.g. (panorama name, line); a repeat raises
    ValueError naming the file, the `what` ("panorama") and both lines."""
    seen: dict[str, int] = {}
    for key, line in keyed:
        if key in seen:
            raise ValueError(f"{path}:{line}: {what} {key} is listed again (first on line {seen[key]}); a "
                             f"{what} listed twice would be counted twice: keep one of lines {seen[key]} and {line}")
        seen[key] = line
