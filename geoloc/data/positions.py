"""Where each place is: the optional `positions.csv` of a CVUSA-layout folder, read into a RetrievalSplit.

CVUSA's released split files carry no coordinates, so geoloc reads them, when present, from its own file
`ROOT/positions.csv`: a header `panorama,x_m,y_m` (metres in one projected frame, e.g. UTM easting / northing) or
`panorama,lat,lon` (degrees), then one row per panorama path as the split files spell it. The synthetic layouts
write it (docs/datasets.md). A query and its aerial tile share the position (the tile is centred on the camera).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geoloc.data.list_files import csv_rows, refuse_repeats

POSITIONS_FILE = "positions.csv"
HEADERS = {("panorama", "x_m", "y_m"): "xy", ("panorama", "lat", "lon"): "latlon"}


def positions_text(rows: list[tuple[str, float, float]], kind: str = "xy") -> str:
    """The text of `positions.csv` for (panorama path, a, b) rows: a, b = x_m, y_m (kind "xy") or lat, lon."""
    header = next(h for h, k in HEADERS.items() if k == kind)
    return ",".join(header) + "\n" + "".join(f"{p},{a:.6f},{b:.6f}\n" for p, a, b in rows)


def read_positions(root: Path, queries: list[Path]) -> tuple[str, np.ndarray] | None:
    """(kind, Q x 2 array) for the queries (paths under root), or None when root has no positions.csv.

    kind is "xy" (metres) or "latlon" (degrees). A query missing from the file is an error naming it.
    """
    path = Path(root) / POSITIONS_FILE
    if not path.is_file():
        return None
    rows = csv_rows(path, "positions file")
    kind = HEADERS.get(tuple(c.strip() for c in rows[0][1])) if rows else None
    if kind is None:
        raise ValueError(f"{path}: the first line must be one of "
                         f"{[','.join(h) for h in HEADERS]}, got {','.join(rows[0][1]) if rows else 'an empty file'!r}")
    table = {}
    for line, row in rows[1:]:
        try:
            table[row[0].strip()] = (float(row[1]), float(row[2]))
        except (IndexError, ValueError) as err:
            raise ValueError(f"{path} line {line}: expected 'panorama,number,number', got {','.join(row)!r}") from err
    refuse_repeats(path, [(row[0].strip(), line) for line, row in rows[1:]], "panorama")
    out = np.empty((len(queries), 2), np.float64)
    for i, q in enumerate(queries):
        key = Path(q).relative_to(root).as_posix()
        if key not in table:
            raise ValueError(f"{path} has no row for {key}: list every panorama of the splits, or remove the file")
        out[i] = table[key]
    return kind, out
