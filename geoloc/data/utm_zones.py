"""UTM zones as the own-data tables and VPR file names give them: which positions share one metric frame.

A zone is written as its number (1-60) and optionally its latitude band letter (C-X without I and O), e.g. `32T`
or `32`. Eastings and northings are one frame across a zone's bands of one hemisphere (the letters C-M lie south
of the equator, N-X north of it, and the south's northings carry a 10,000 km false northing). Two zones agree
when their numbers are equal and, where both letters are given, their hemispheres are; a zone without its letter
agrees with every band of its number.
"""

from __future__ import annotations

import re

BANDS = "CDEFGHJKLMNPQRSTUVWX"
_ZONE = re.compile(rf"(\d{{1,2}})([{BANDS}]?)")


def parse_zone(text: str, where: str) -> str | None:
    """`text` as a zone ("32T", "32"), None when empty; a ValueError naming `where` when it is not a UTM zone."""
    text = text.strip().upper()
    if not text:
        return None
    found = _ZONE.fullmatch(text)
    if found is None or not 1 <= int(found[1]) <= 60:
        raise ValueError(f"{where}: UTM zone {text!r} is not a zone: a number from 1 to 60, optionally with its "
                         f"latitude band letter ({BANDS[0]}-{BANDS[-1]}, no I or O), e.g. 32T")
    return f"{int(found[1])}{found[2]}"


def _frame(zone: str) -> tuple[int, str | None]:
    """(number, hemisphere "N" | "S", or None without a letter) of a parsed zone."""
    number, letter = int(zone.rstrip(BANDS)), zone.lstrip("0123456789")
    return number, (None if not letter else "N" if letter >= "N" else "S")


def same_frame(a: str, b: str) -> bool:
    """Whether positions in parsed zones `a` and `b` share one metric frame (module docstring)."""
    (number_a, half_a), (number_b, half_b) = _frame(a), _frame(b)
    return number_a == number_b and (half_a is None or half_b is None or half_a == half_b)


def one_zone(zones: list[tuple[str, str]]) -> str | None:
    """The zone that (parsed zone, where) pairs share, the first with its letter where any has one; None for no
    pair; a ValueError naming the first pair that differs."""
    if not zones:
        return None
    first, first_where = zones[0]
    for zone, where in zones:
        if not same_frame(zone, first):
            raise ValueError(f"{where}: UTM zone {zone} differs from {first} ({first_where}); metres of two zones "
                             "are two frames and their distances are wrong: give positions in one zone, or as lat,lon")
        if _frame(first)[1] is None and _frame(zone)[1] is not None:
            first, first_where = zone, where
    return first
