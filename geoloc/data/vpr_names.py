"""Positions from VPR file names, read as gmberton's VPR-methods-evaluation reads them (its test_dataset.py).

The name form of the VPR tools (VPR-datasets-downloader, SF-XL, MeshSynth) is
`@UTM_east@UTM_north@UTM_zone_number@UTM_zone_letter@lat@lon@...@.jpg`. The reference reads the '@'-separated
field 1 as the easting and field 2 as the northing (metres) and nothing else, so `@500123.4@4649876.5@.jpg` is a
whole name, and whatever stands before the first '@' is not read. Here too; besides, the UTM zone (fields 3 and 4)
is read where it is given, so that positions of two zones are refused rather than measured across two frames
(geoloc/data/utm_zones.py). lat, lon and the fields after them are not read: they may be present, empty or absent.

The reference splits the whole path at '@'; this splits the file name, so the two agree for any path whose folders
hold no '@'.
"""

from __future__ import annotations

import math
from pathlib import Path

from geoloc.data.utm_zones import parse_zone

FORM = ("'@UTM_east@UTM_north@.jpg' or '@UTM_east@UTM_north@UTM_zone_number@UTM_zone_letter@lat@lon@...@.jpg' "
        "(east and north in metres; the fields after north optional)")


def vpr_position(name: str, where: str) -> tuple[float, float, str | None]:
    """(east, north, UTM zone or None) of the file name of `name`; a ValueError naming `where` and the form
    otherwise."""
    fields = Path(name).name.split("@")
    try:
        east, north = float(fields[1]), float(fields[2])
    except (IndexError, ValueError):
        east = north = math.nan
    if not (math.isfinite(east) and math.isfinite(north)):
        raise ValueError(f"{where}: {Path(name).name!r} is not a VPR name {FORM}")
    optional = fields[3:-1]  # the last field is the extension's, e.g. '.jpg'
    number = optional[0] if optional else ""
    letter = optional[1] if len(optional) > 1 and number.strip() else ""
    return east, north, parse_zone(number + letter, f"{where}: the zone fields of {Path(name).name!r}")
