"""What the readers share: a one-to-one split from pairs, and their start-up refusals."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from geoloc.config import ConfigError
from geoloc.data.retrieval_split import RetrievalSplit


def pairs_split(name: str, root, pairs: list[tuple[Path, Path]], query_view: str = "panorama",
                positions: tuple[str, np.ndarray] | None = None,
                tile: tuple[int, float | None] | None = None) -> RetrievalSplit:
    """A one-to-one split from (street, aerial) pairs: query i matches reference i. positions: (kind, P x 2),
    kind "xy" (metres) or "latlon" (degrees), where pair i was taken; its query and reference share it.
    tile: (side in pixels, metres per pixel or None) of the square aerial tiles, each centred on its camera (the
    label set "tile_centre")."""
    where = {}
    if positions is not None:
        kind, array = positions
        where = {f"query_{kind}": array, f"reference_{kind}": array}
    if tile is not None:
        side, scale = tile
        where.update(reference_size_px=np.full((len(pairs), 2), side, np.int64),
                     reference_metres_per_px=None if scale is None else np.full(len(pairs), float(scale)),
                     query_tile_px=np.full((len(pairs), 2), side / 2), tile_labels="tile_centre")
    return RetrievalSplit(name=name, root=Path(root), queries=[street for street, _ in pairs],
                          references=[aerial for _, aerial in pairs], positives=np.arange(len(pairs)),
                          query_view=query_view, **where)


def tile_frame(root, released_px: int) -> tuple[int, float | None]:
    """(side in pixels, metres per pixel or None) of a dataset's aerial tiles: a geoloc synthetic tree's, from its
    marker (geoloc.synthetic.tile_geometry); otherwise the release's side, at a scale this does not know."""
    from geoloc.synthetic import tile_geometry

    geometry = tile_geometry(root)
    return (released_px, None) if geometry is None else geometry


def with_view(split: RetrievalSplit, view: str) -> RetrievalSplit:
    return replace(split, query_view=view)


def require_root(root, name: str) -> None:
    if not root:
        raise ConfigError(f"dataset={name} needs dataset.root=/path/to/{name.upper()} (it is missing); the embedded "
                          "synthetic data is dataset=synthetic, vigor or u1652 with no root")


def check_split(dataset: str, split: str, splits) -> None:
    """A split name the dataset does not have is refused, listing the ones it has (CVUSA: train/val, where CVACT
    has a test split too)."""
    if split not in splits:
        raise ConfigError(f"dataset.split={split!r} is not a split of {dataset}: split must be one of "
                          f"{list(splits)} (CVUSA and the embedded synthetic data: train, val; CVACT: train, val, "
                          "test; VIGOR and University-1652: train, test)")
