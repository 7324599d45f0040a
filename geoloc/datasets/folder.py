"""Your own data: a folder of street images and a folder of aerial tiles with their positions -> RetrievalSplit.

    ROOT/queries/...        street images (north-aligned panoramas, as CVUSA's, unless query_view says otherwise)
    ROOT/tiles/...          aerial tiles, north up, each centred on its position
    ROOT/queries.csv        image,lat,lon | image,east_m,north_m[,utm_zone]   (geoloc/data/place_tables.py)
    ROOT/tiles.csv          the same columns: the tile centre

Without a CSV, the folder's file names must carry their position the VPR tools' way (`@UTM_east@UTM_north@.jpg`,
zone, lat, lon, ... optional: geoloc/data/vpr_names.py). Queries and tiles must use one coordinate system.

A query's positive is its nearest tile (what training pairs it with). Which tiles are relevant, `relevance`:
- ``radius`` (the default): the tiles within `radius_m` (25 m, inclusive) of the query and nothing else, as gmberton's
  VPR-methods-evaluation draws them, so recall is comparable with its numbers. A query with no tile that near has
  nothing to find: a miss at every K, counted in every recall (geoloc/eval/scoring.py);
- ``nearest_tile``: the positive, whatever its distance, and every tile within `radius_m` too.

Tile geometry: `tile_extent_m` (the ground width a tile covers) or `metres_per_px`; the pixel size comes from each
tile's header. Each query's position in its positive tile (RetrievalSplit.query_tile_px) follows. A query outside
its nearest tile (no tile shows it) is refused under ``nearest_tile``, and by split=train under either rule, as a
training pair needs a tile that shows its query. Under ``radius`` split=test and split=all keep it, as the
reference keeps every query: its position in a tile is unknown (NaN), and the fine-grained metrics skip it and say
how many they skip (geoloc/tasks/crossview/refine.py).

Splits are by area, never at random: the tile centres are projected on `split_axis` (east or north, metres in a
local frame), and the tiles beyond the (1 - test_fraction) quantile form the test area; a query belongs to the
area of its nearest tile. split=all reads everything (evaluating a trained model on your region).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geoloc.config import ConfigError
from geoloc.data.geo import centre_latlon, distance_m, latlon_to_offset
from geoloc.data.place_tables import PlaceTable, read_places
from geoloc.data.relevance import RADIUS_M
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.data.utm_zones import same_frame
from geoloc.registry import register

SPLITS = ("train", "test", "all")
RELEVANCE_RULES = ("radius", "nearest_tile")
AXES = ("east", "north")
QUERY_VIEWS = ("panorama", "sphere", "image")
QUERY_DIR, TILE_DIR = "queries", "tiles"


def local_metres(kind: str, positions: np.ndarray, origin) -> np.ndarray:
    """(N, 2) (east, north) metres of positions of `kind` around `origin` (lat, lon for "latlon"; the "xy" frame is
    kept as it is)."""
    return positions if kind == "xy" else latlon_to_offset(origin, positions)


def nearest(query_positions: np.ndarray, tile_positions: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """(Q,) index of each query's nearest tile and (Q,) its distance in metres (the first on ties)."""
    index, metres = np.empty(len(query_positions), np.int64), np.empty(len(query_positions))
    step = max(1, (1 << 22) // len(tile_positions))
    for q0 in range(0, len(query_positions), step):
        d = distance_m(query_positions[q0:q0 + step, None], tile_positions[None], kind)
        index[q0:q0 + step] = d.argmin(1)
        metres[q0:q0 + step] = d.min(1)
    return index, metres


def tile_sizes(tiles: PlaceTable, index: np.ndarray) -> np.ndarray:
    """(len(index), 2) (height, width) pixels of tiles[index], from each file's header."""
    from PIL import Image, UnidentifiedImageError

    out = np.empty((len(index), 2), np.int64)
    for k, i in enumerate(index):
        try:
            with Image.open(tiles.paths[i]) as image:
                out[k] = image.size[1], image.size[0]
        except (OSError, UnidentifiedImageError) as err:
            raise ValueError(f"{tiles.where(i)}: tile {tiles.paths[i]} cannot be read as an image ({err}); replace "
                             "it, or remove it and its row") from None
    return out


def test_area(east_north: np.ndarray, axis: str, fraction: float) -> tuple[np.ndarray, float]:
    """(N,) bool: the tiles in the test area, and the line: the tiles whose `axis` coordinate is at least the
    (1 - fraction) quantile of all (numpy's linear interpolation)."""
    coordinate = east_north[:, AXES.index(axis)]
    line = float(np.quantile(coordinate, 1.0 - fraction))
    return coordinate >= line, line


def folder_split(root, split: str, tile_extent_m: float | None, metres_per_px: float | None, radius_m: float,
                 relevance: str, split_axis: str, test_fraction: float, query_view: str) -> RetrievalSplit:
    """The split of the module docstring; the keys as `folder` takes them, defaults there."""
    root = Path(root)
    _check_keys(split, tile_extent_m, metres_per_px, radius_m, relevance, split_axis, test_fraction, query_view)
    queries = read_places(root / QUERY_DIR, root / f"{QUERY_DIR}.csv")
    tiles = read_places(root / TILE_DIR, root / f"{TILE_DIR}.csv")
    if queries.kind != tiles.kind:
        raise ValueError(f"{queries.source} gives {_system_name(queries.kind)} and {tiles.source} gives "
                         f"{_system_name(tiles.kind)}: give both in one coordinate system")
    if queries.zone and tiles.zone and not same_frame(queries.zone, tiles.zone):
        raise ValueError(f"{queries.source} is in UTM zone {queries.zone} and {tiles.source} in {tiles.zone}: give "
                         "both in one zone, or as lat,lon")
    kind = tiles.kind
    origin = centre_latlon(tiles.positions) if kind == "latlon" else tiles.positions.mean(0)
    tile_en = local_metres(kind, tiles.positions, origin)
    keep = np.ones(len(tiles.paths), bool)
    name = f"folder/{split}"
    if split != "all":
        in_test, line = test_area(tile_en, split_axis, test_fraction)
        keep = in_test if split == "test" else ~in_test
        name += f" ({split_axis} {'>=' if split == 'test' else '<'} {line:.1f} m)"
    nearest_all, _ = nearest(queries.positions, tiles.positions, kind)
    chosen = np.flatnonzero(keep[nearest_all])
    if len(chosen) == 0 or not keep.any():
        raise ValueError(f"{root}: the {split} area ({name}) holds no tile or no query: change test_fraction or "
                         "split_axis, or add images there")
    tile_index = np.flatnonzero(keep)
    query_pos, tile_pos = queries.positions[chosen], tiles.positions[tile_index]
    positives, metres = nearest(query_pos, tile_pos, kind)
    size = tile_sizes(tiles, tile_index)
    scale = (np.full(len(tile_index), float(metres_per_px)) if metres_per_px is not None
             else float(tile_extent_m) / size[:, 1])
    # (east, north) metres of each query from its tile's centre
    offset = local_metres(kind, query_pos, origin) - tile_en[tile_index][positives]
    row = size[positives, 0] / 2 - offset[:, 1] / scale[positives]
    col = size[positives, 1] / 2 + offset[:, 0] / scale[positives]
    outside = (row < 0) | (row > size[positives, 0]) | (col < 0) | (col > size[positives, 1])
    if outside.any() and (relevance == "nearest_tile" or split == "train"):
        i = int(np.flatnonzero(outside)[0])
        extent = size[positives[i]] * scale[positives[i]]
        why = (" split=train pairs each query with a tile that shows it (split=test and split=all keep such a "
               "query under relevance=radius).") if relevance == "radius" else ""
        raise ValueError(f"{queries.where(int(chosen[i]))}: query {queries.paths[chosen[i]]} lies {metres[i]:.1f} m "
                         f"from its nearest tile's centre ({tiles.paths[tile_index[positives[i]]]}), outside that "
                         f"tile ({extent[1]:.1f} x {extent[0]:.1f} m): no tile shows it ({int(outside.sum())} such "
                         f"queries).{why} Add tiles covering it, remove it, or check tile_extent_m / metres_per_px")
    tile_px = np.column_stack([row, col])
    tile_px[outside] = np.nan  # no tile shows the query: its position in a tile is unknown
    where = {f"query_{kind}": query_pos, f"reference_{kind}": tile_pos}
    return RetrievalSplit(name=name, root=root, queries=[queries.paths[i] for i in chosen],
                          references=[tiles.paths[i] for i in tile_index], positives=positives,
                          query_view=query_view, relevance_radius_m=float(radius_m),
                          radius_alone=relevance == "radius", reference_size_px=size, reference_metres_per_px=scale,
                          query_tile_px=tile_px, tile_labels="positions", **where)


def _system_name(kind: str) -> str:
    return "lat,lon (degrees)" if kind == "latlon" else "east_m,north_m (metres)"


def _check_keys(split, tile_extent_m, metres_per_px, radius_m, relevance, split_axis, test_fraction,
                query_view) -> None:
    if split not in SPLITS:
        raise ConfigError(f"dataset=folder: split must be one of {list(SPLITS)}, got {split!r}")
    if relevance not in RELEVANCE_RULES:
        raise ConfigError(f"dataset=folder: relevance must be one of {list(RELEVANCE_RULES)} (radius: the tiles "
                          f"within radius_m alone; nearest_tile: the nearest tile too), got {relevance!r}")
    if not np.isfinite(radius_m) or radius_m < 0:
        raise ConfigError(f"dataset=folder: radius_m must be a finite number of metres >= 0, got {radius_m}")
    if (tile_extent_m is None) == (metres_per_px is None):
        raise ConfigError("dataset=folder needs the tiles' ground scale, one of dataset.tile_extent_m (the metres a "
                          "tile's width covers) or dataset.metres_per_px, not both; "
                          f"got tile_extent_m={tile_extent_m}, metres_per_px={metres_per_px} (an evaluation keeps the "
                          "checkpoint's value of the key it does not set: give the key it was trained with)")
    scale = tile_extent_m if tile_extent_m is not None else metres_per_px
    if not np.isfinite(scale) or scale <= 0:
        raise ConfigError(f"dataset=folder: the tile scale must be a positive number of metres, got {scale}")
    if split_axis not in AXES:
        raise ConfigError(f"dataset=folder: split_axis must be one of {list(AXES)}, got {split_axis!r}")
    if not 0.0 < test_fraction < 1.0:
        raise ConfigError(f"dataset=folder: test_fraction must lie in (0, 1), got {test_fraction}")
    if query_view not in QUERY_VIEWS:
        raise ConfigError(f"dataset=folder: query_view must be one of {list(QUERY_VIEWS)}, got {query_view!r}")


@register("dataset", "folder")
def folder(root: str | None, split: str, tile_extent_m: float | None = None, metres_per_px: float | None = None,
           radius_m: float = RADIUS_M, relevance: str = "radius", split_axis: str = "east",
           test_fraction: float = 0.25, query_view: str = "panorama") -> RetrievalSplit:
    """Your own street images and aerial tiles (module docstring); split = train | test (by area) | all;
    relevance = radius (the tiles within radius_m alone) | nearest_tile (the nearest tile too)."""
    if not root:
        raise ConfigError("dataset=folder needs dataset.root=DIR holding queries/ and tiles/ (docs/datasets.md "
                          "'Your own data')")
    return folder_split(root, "test" if split == "val" else split, tile_extent_m, metres_per_px, radius_m,
                        relevance, split_axis, test_fraction, query_view)
