"""A route's odometry: how far and how the camera turned between consecutive frames, read from `odometry.csv`.

The file has the header `frame,distance_m,heading_change_deg` (in any order; other columns are ignored) and one row
per frame, frames 0, 1, ..., F-1 in order. Row i is the motion from frame i-1 to frame i: the camera turns by
heading_change_deg (clockwise positive, as headings are measured from north) and then travels distance_m metres.
Row 0 has no motion before it and is `0,0,0`: a file whose first row moves is one row out of step with its frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoloc.data.list_files import csv_lines, csv_rows, text_lines

ODOMETRY_FILE = "odometry.csv"
COLUMNS = ("frame", "distance_m", "heading_change_deg")


@dataclass(frozen=True)
class Motion:
    """The motion into one frame: turn by heading_change_deg (clockwise), then travel distance_m metres."""

    distance_m: float
    heading_change_deg: float


@dataclass(frozen=True)
class Odometry:
    """distance_m, heading_change_deg: (F,) the motion into each frame, entry 0 zero."""

    distance_m: np.ndarray
    heading_change_deg: np.ndarray

    def __len__(self) -> int:
        return len(self.distance_m)

    def motion(self, frame: int) -> Motion:
        return Motion(float(self.distance_m[frame]), float(self.heading_change_deg[frame]))


def odometry_text(distance_m, heading_change_deg) -> str:
    """The text of `odometry.csv` for (F,) distances and heading changes (entry 0 zero)."""
    rows = "".join(f"{i},{d:.6f},{h:.6f}\n" for i, (d, h) in enumerate(zip(distance_m, heading_change_deg)))
    return ",".join(COLUMNS) + "\n" + rows


def read_odometry(path: str | Path) -> Odometry:
    """The Odometry of `path` (an odometry.csv); every fault is a ValueError naming the file, the line, what is wrong
    and what to write instead."""
    path = Path(path)
    return odometry_of_rows(csv_rows(path, "odometry file"), path)


def parse_odometry(data: bytes, name: str) -> Odometry:
    """read_odometry of an odometry.csv's bytes that came without a file (an upload), `name`d in every refusal."""
    named = f"the upload {name!r}"
    return odometry_of_rows(csv_lines(text_lines(data, named), named), named)


def odometry_of_rows(rows: list[tuple[int, list[str]]], path) -> Odometry:
    """The Odometry of an odometry.csv's (line number, fields) rows; `path` names it in every refusal."""
    if not rows:
        raise ValueError(f"{path} is empty: write the header {','.join(COLUMNS)} and one row per frame")
    header_line, header = rows[0]
    names = [name.strip() for name in header]
    missing = [c for c in COLUMNS if c not in names]
    if missing:
        raise ValueError(f"{path}:{header_line}: the header has no column {', '.join(missing)} (it reads "
                         f"{','.join(names)!r}); the first line must name {','.join(COLUMNS)}")
    column = {c: names.index(c) for c in COLUMNS}
    if len(rows) == 1:
        raise ValueError(f"{path} has a header but no frames: write one row per frame, starting with 0,0,0")
    distance, turn = [], []
    for expected, (line, row) in enumerate(rows[1:]):
        if len(row) != len(names):
            raise ValueError(f"{path}:{line}: {len(row)} fields where the header names {len(names)}: "
                             f"{','.join(row)!r}")
        values = {c: _number(path, line, c, row[column[c]]) for c in COLUMNS}
        if values["frame"] != expected:
            raise ValueError(f"{path}:{line}: frame {row[column['frame']].strip()} where frame {expected} was "
                             "expected: the rows must be frames 0, 1, 2, ... in order, one row per frame")
        if values["distance_m"] < 0:
            raise ValueError(f"{path}:{line}: distance_m is {values['distance_m']}, below 0: a distance travelled "
                             "is never negative (a reverse is a heading change of 180 degrees and a positive distance)")
        if expected == 0 and (values["distance_m"] != 0 or values["heading_change_deg"] != 0):
            raise ValueError(f"{path}:{line}: frame 0 moves ({row[column['distance_m']].strip()} m, "
                             f"{row[column['heading_change_deg']].strip()} degrees), but nothing comes before it: "
                             "row i is the motion from frame i-1 to frame i, so row 0 is 0,0,0")
        distance.append(values["distance_m"])
        turn.append(values["heading_change_deg"])
    return Odometry(np.array(distance), np.array(turn))


def _number(path, line: int, name: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{path}:{line}: {name} is {text.strip()!r}, not a number: write it in decimal "
                         "(e.g. 9.85)") from None
    if not np.isfinite(value):
        raise ValueError(f"{path}:{line}: {name} is {text.strip()!r}: it must be a finite number")
    if name == "frame" and value != int(value):
        raise ValueError(f"{path}:{line}: frame is {text.strip()!r}: frames are whole numbers 0, 1, 2, ...")
    return value
