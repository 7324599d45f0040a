"""VIGOR-layout offsets unrounded: geoloc's own `ROOT/geoloc_offsets.json`, which the synthetic vigor tree writes and
the VIGOR reader reads when present.

A VIGOR split line gives each (panorama, tile) offset rounded to whole pixels; the file gives the same offsets to
full precision, so a metre-level target can be measured:

    {"offsets": {"<City>": {"<panorama file name>": {"<satellite file name>": [north, east], ...}, ...}, ...}}

north, east: the tile centre minus the panorama, in pixels of the tile (the split lines' convention).
"""

from __future__ import annotations

import json
from pathlib import Path

OFFSETS_FILE = "geoloc_offsets.json"


def offsets_text(offsets: dict) -> str:
    """The file's text for {city: {panorama: {satellite: [north, east]}}} (floats written round-trip exact)."""
    return json.dumps({"offsets": offsets}, indent=0) + "\n"


def read_offsets(root) -> dict | None:
    """{city: {panorama: {satellite: [north, east]}}} of ROOT/geoloc_offsets.json, or None when there is none."""
    path = Path(root) / OFFSETS_FILE
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())["offsets"]
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise ValueError(f"{path} is not a geoloc offsets file ({err}); delete it and load the synthetic dataset "
                         "again to have it rewritten") from err
