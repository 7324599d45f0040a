"""Where each image of a folder was taken: a positions CSV, or the VPR tools' file names.

A positions CSV (`queries.csv` for street images, `tiles.csv` for aerial tiles, the tile centre) has a header and one
row per image, in one of two coordinate systems:
- `image,lat,lon`: WGS84 degrees;
- `image,east_m,north_m` (optionally `,utm_zone`, e.g. `32T`, one zone on every row): metres in one projected frame,
  e.g. UTM easting / northing.
`image` is the file's path under the folder (sub-folders allowed). The columns may come in any order; any other
column is refused.

Without a CSV, the file names give the positions the VPR tools' way (geoloc/data/vpr_names.py):
`@UTM_east@UTM_north@.jpg`, or with the optional fields `@UTM_east@UTM_north@UTM_zone_number@UTM_zone_letter@lat@lon@
...@.jpg`. The UTM metres are the positions, as the VPR tools measure distances in them; the zones given must agree
(geoloc/data/utm_zones.py).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoloc.data.list_files import csv_rows, refuse_repeats
from geoloc.data.utm_zones import one_zone, parse_zone
from geoloc.data.vpr_names import vpr_position

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
SYSTEMS = {"latlon": ("lat", "lon"), "xy": ("east_m", "north_m")}
ZONE_COLUMN = "utm_zone"
HEADERS = ("image,lat,lon", "image,east_m,north_m", "image,east_m,north_m,utm_zone")


@dataclass(frozen=True)
class PlaceTable:
    """Images of one folder and where each was taken.

    paths: N absolute paths; kind: "latlon" (degrees) or "xy" (metres); positions: (N, 2) (lat, lon) or
    (east, north); zone: the UTM zone ("32T", "32") of "xy" positions when any is given; source: the CSV or the folder read,
    for messages; lines: the CSV line of each image (0 for a VPR name)."""

    paths: list
    kind: str
    positions: np.ndarray
    zone: str | None
    source: Path
    lines: list

    def where(self, i: int) -> str:
        return f"{self.source}:{self.lines[i]}" if self.lines[i] else str(self.paths[i])


def image_files(folder: Path) -> list[Path]:
    """Every image (IMAGE_SUFFIXES, any case) under `folder`, in sorted path order; each name must be UTF-8."""
    found = sorted(p for p in Path(folder).rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    for path in found:
        require_utf8_name(path, folder)
    return found


def require_utf8_name(path: Path, folder: Path) -> None:
    """A ValueError naming `path` when its name under `folder` is not UTF-8 (Python reads such bytes as lone
    surrogates). The names go into UTF-8 text (a gallery's reference list and its sha256, the service's answers and
    page), which cannot hold them, so they are refused here rather than carried as bytes through every writer."""
    name = Path(path).relative_to(folder).as_posix()
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError(f"{folder}: the file name {os.fsencode(name)!r} is not UTF-8: geoloc writes image names into "
                         "UTF-8 files (a saved gallery's references, the service's answers), which cannot hold it. "
                         f"Rename it in UTF-8 (e.g. convmv -f latin1 -t utf-8 -r --notest {folder})") from None


def read_places(folder: Path, table: Path) -> PlaceTable:
    """The images of `folder` with their positions: from the CSV `table` when it exists, otherwise from VPR file
    names. Every image of the folder must be placed, and every row must name an image of the folder."""
    folder, table = Path(folder), Path(table)
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder {folder} not found: the own-data layout is ROOT/queries/ (street "
                                "images) and ROOT/tiles/ (aerial tiles) (docs/datasets.md 'Your own data')")
    found = image_files(folder)
    if not found:
        raise ValueError(f"{folder} holds no image ({', '.join(IMAGE_SUFFIXES)})")
    places = _from_csv(folder, table) if table.is_file() else _from_names(folder, found, table)
    listed = {Path(p) for p in places.paths}
    extra = [p for p in found if p not in listed]
    if extra:
        raise ValueError(f"{extra[0]} is in {folder} but not in {places.source} ({len(extra)} such images): add a "
                         "row for each, or move them out of the folder, so no image is left out without notice")
    return places


def _from_csv(folder: Path, table: Path) -> PlaceTable:
    rows = csv_rows(table, "positions table")
    if not rows:
        raise ValueError(f"{table} is empty; its first line is the header, one of {list(HEADERS)}")
    header_line, header = rows[0]
    columns = [c.strip() for c in header]
    kind = _system(table, header_line, columns)
    if len(set(columns)) != len(columns):
        raise ValueError(f"{table}:{header_line}: a column is named twice in {','.join(columns)}")
    image_at = columns.index("image")
    a_at, b_at = (columns.index(c) for c in SYSTEMS[kind])
    zone_at = columns.index(ZONE_COLUMN) if ZONE_COLUMN in columns else None
    paths, positions, zones, lines = [], [], [], []
    for line, row in rows[1:]:
        where = f"{table}:{line}"
        if len(row) != len(columns):
            raise ValueError(f"{where}: {len(row)} fields, the header has {len(columns)} ({','.join(columns)}): "
                             f"{','.join(row)[:120]!r}")
        name = row[image_at].strip()
        path = folder / name
        if not name or Path(name).is_absolute() or ".." in Path(name).parts:
            raise ValueError(f"{where}: image {name!r} must be a path under {folder} (no absolute path, no '..')")
        if not path.is_file():
            raise FileNotFoundError(f"{where}: image {name} not found in {folder}; fix the name or remove the row")
        try:
            a, b = float(row[a_at]), float(row[b_at])
        except ValueError:
            raise ValueError(f"{where}: {SYSTEMS[kind][0]},{SYSTEMS[kind][1]} must be numbers, got "
                             f"{row[a_at]!r},{row[b_at]!r}") from None
        if not (math.isfinite(a) and math.isfinite(b)):
            raise ValueError(f"{where}: the position {a},{b} is not a finite number")
        if kind == "latlon" and (abs(a) > 90 or abs(b) > 180):
            raise ValueError(f"{where}: lat,lon = {a},{b} is not a position in degrees (|lat| <= 90, |lon| <= 180); "
                             "metres (e.g. UTM) go in a file with the header image,east_m,north_m, and one file "
                             "holds one coordinate system")
        zone = parse_zone(row[zone_at], where) if zone_at is not None else None
        if zone is not None:
            zones.append((zone, where))
        paths.append(path)
        positions.append((a, b))
        lines.append(line)
    if not paths:
        raise ValueError(f"{table} has a header and no row: list each image of {folder} with its position")
    refuse_repeats(table, [(Path(p).relative_to(folder).as_posix(), k) for p, k in zip(paths, lines)], "image")
    return PlaceTable(paths, kind, np.asarray(positions, np.float64), one_zone(zones), table, lines)


def _system(table: Path, line: int, columns: list[str]) -> str:
    known = {"image", ZONE_COLUMN, *SYSTEMS["latlon"], *SYSTEMS["xy"]}
    unknown = [c for c in columns if c not in known]
    kinds = [k for k, pair in SYSTEMS.items() if set(pair) <= set(columns)]
    partial = [k for k, pair in SYSTEMS.items() if set(pair) & set(columns)]
    if unknown or "image" not in columns or len(kinds) != 1 or len(partial) != 1 or (
            ZONE_COLUMN in columns and kinds != ["xy"]):
        why = (f"unknown column {unknown[0]!r}" if unknown else "no image column" if "image" not in columns
               else "both lat/lon and east_m/north_m columns (one file holds one coordinate system)"
               if len(partial) > 1 else f"{ZONE_COLUMN} goes with east_m,north_m" if ZONE_COLUMN in columns
               and kinds == ["latlon"] else "no complete position (lat,lon or east_m,north_m)")
        raise ValueError(f"{table}:{line}: header {','.join(columns)!r}: {why}. The header is one of "
                         f"{list(HEADERS)}, columns in any order (docs/datasets.md 'Your own data')")
    return kinds[0]


def _from_names(folder: Path, found: list[Path], table: Path) -> PlaceTable:
    try:
        parsed = [vpr_position(p.name, str(p)) for p in found]
    except ValueError as err:
        raise ValueError(f"{err}. Write {table} (header one of {list(HEADERS)}), or name the files the VPR way "
                         "(docs/datasets.md 'Your own data')") from None
    zone = one_zone([(z, str(p)) for p, (_, _, z) in zip(found, parsed) if z is not None])
    return PlaceTable(found, "xy", np.asarray([(e, n) for e, n, _ in parsed], np.float64), zone, folder,
                      [0] * len(found))
