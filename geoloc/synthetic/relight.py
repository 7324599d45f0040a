"""One city of a rendered synthetic VIGOR world under another sun or season: the same places, written as a new
dataset root, for diagnosis (docs/datasets.md, "What a new city changes").

The city's satellite tiles are rendered again with the city's aerial conditions changed. Its panoramas are rendered
again too (unless panoramas=False), their conditions drawn around the new ones as the renderer draws them
(appearance.other_time), from the same random streams: every position, name, car and split line stays as it was.
The other cities, the split files and the offsets are linked to the source, which is only read.

    python tools/relight_vigor.py SOURCE OUT --city Chicago --sun-elevation 64
    python evaluate.py ckpt=... dataset=vigor dataset.root=OUT dataset.setting=cross_area "dataset.cities=[Chicago]"
"""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

from .city import CITY_NAMES, build_city
from .world_config import SynthConfig, VigorOptions
from .generate import MARKER, vigor_marker, write_marker
from .vigor_layout import CROSS_AREA_FILE, write_panorama, write_tiles


def relight_city(source, out, city: str, sun_elevation: float | None = None, sun_azimuth: float | None = None,
                 season: float | None = None, panoramas: bool = True) -> Path:
    """Write OUT: the vigor dataset at `source` with `city` rendered again under the changed conditions (None
    keeps the city's own). -> OUT."""
    _check_conditions(sun_elevation, sun_azimuth, season)
    source, out = Path(source).resolve(), Path(out)
    marker = vigor_marker(source, "relight")
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not empty; relight writes a new dataset root, so give a new folder")
    opts = VigorOptions(**marker["options"])
    names = CITY_NAMES[:opts.cities]
    if city not in names:
        raise ValueError(f"{source} has the cities {list(names)}, not {city!r}")
    cfg, seed = SynthConfig(**marker["config"]), int(marker["seed"])
    own = build_city(cfg, opts.grid, seed, names.index(city))
    sun = own.aerial.sun
    sun = replace(sun, elevation=sun.elevation if sun_elevation is None else float(sun_elevation),
                  azimuth=sun.azimuth if sun_azimuth is None else float(sun_azimuth) % 360.0)
    changed = replace(own, aerial=replace(own.aerial, sun=sun, season=own.aerial.season if season is None
                                          else float(season)))
    out.mkdir(parents=True, exist_ok=True)
    for entry in source.iterdir():
        if entry.name not in (city, MARKER):
            (out / entry.name).symlink_to(entry)
    write_tiles(cfg, changed, seed, out)
    panorama_dir = out / city / "panorama"
    if panoramas:
        lines = [write_panorama(cfg, changed, seed, split, k, out)
                 for split, count in (("train", marker["train"]), ("val", marker["val"])) for k in range(count)]
        expected = (source / "splits" / city / CROSS_AREA_FILE).read_text().splitlines()
        if lines != expected:
            raise RuntimeError(f"the panoramas rendered again for {city} do not stand where {source}'s split file "
                               "says: the source was rendered by another version of the renderer")
    else:
        panorama_dir.symlink_to(source / city / "panorama")
    relit = {"source": str(source), "city": city, "sun_azimuth": sun.azimuth, "sun_elevation": sun.elevation,
             "season": changed.aerial.season, "panoramas": panoramas,
             "was": {"sun_azimuth": own.aerial.sun.azimuth, "sun_elevation": own.aerial.sun.elevation,
                     "season": own.aerial.season}}
    # written last, as the renderer does: a folder without it is unfinished (geoloc.synthetic.tile_geometry)
    write_marker(out, {**marker, "relit": relit}, complete=True)
    return out


def _check_conditions(sun_elevation, sun_azimuth, season) -> None:
    """Each condition given is a finite number in its range, checked before anything is read or written: a sun of
    NaN or infinite azimuth lights no pixel, and the render would be black tiles under a marker holding NaN."""
    ranges = {"sun_elevation": (sun_elevation, "(0, 90] degrees", lambda v: 0.0 < v <= 90.0),
              "sun_azimuth": (sun_azimuth, "[0, 360] degrees clockwise from north", lambda v: 0.0 <= v <= 360.0),
              "season": (season, "[0, 1] (0 summer .. 1 winter)", lambda v: 0.0 <= v <= 1.0)}
    for name, (value, allowed, inside) in ranges.items():
        if value is not None and not (math.isfinite(value) and inside(value)):
            raise ValueError(f"{name} must be a number in {allowed}, got {value}; nothing was written")
