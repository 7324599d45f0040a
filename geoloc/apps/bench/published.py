"""The published figures (published.yaml, shipped with the package) and the ones that match a row's protocol."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import yaml

FILE = Path(__file__).with_name("published.yaml")


@lru_cache(maxsize=1)
def published() -> dict:
    """{"anchors": [...], "not_entered": {...}} as the file holds them."""
    return yaml.safe_load(FILE.read_text())


def matching(test_set: str, fov: float, heading: str) -> list[dict]:
    """The anchors measured on `test_set` at `fov` with the heading `heading`: the figures that stand beside the
    row of that protocol."""
    return [a for a in published()["anchors"]
            if a["test_set"] == test_set and float(a["fov"]) == float(fov) and a["heading"] == heading]


def source(anchor: dict) -> str:
    """The anchor's source in one line: paper, where in it, protocol."""
    return (f"{anchor['method']}: {anchor['paper']}; {anchor['where']}; {anchor['test_set']}, FoV "
            f"{float(anchor['fov']):g}, heading {anchor['heading']}")
