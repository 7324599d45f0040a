"""A tile with a margin of ground around it, stitched from the tiles beside it.

VIGOR's satellite tiles overlap by half: the tile whose centre lies half a tile east of another covers that tile's
eastern half and the half-tile beyond it. So a margin of up to half a tile on every side can be cut from the eight
tiles around a tile, wherever they exist. The refiner reads its tile with such a margin (`refiner.margin`): a camera
near the tile's edge then still has imagery under the part of its view that leaves the tile.

    neighbours = tile_neighbours(latlon, extent_m)          (R, 3, 3) tile indices, -1 where none; [1, 1] itself
    image = stitched(i, neighbours[i], read, margin)        (H + 2 m H) x (W + 2 m W) x 4 uint8: RGB, then 255 where
                                                            imagery lies and 0 where no tile covers the margin
    TileContext.of(split, margin).image(i, side)            the same at side + 2 margin_cells pixels across

Row 0 of the 3 x 3 neighbourhood lies north, column 0 west (as the image's rows and columns run).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from geoloc.data.geo import EARTH_RADIUS_M
from geoloc.data.io import read_rgb

NEIGHBOUR_TOLERANCE = 0.1  # a neighbour's centre lies within this share of a half-tile of where it is expected


def _unit_vectors(latlon: np.ndarray) -> np.ndarray:
    lat, lon = np.radians(latlon[:, 0]), np.radians(latlon[:, 1])
    return np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])


def tile_neighbours(positions, extent_m, kind: str = "latlon", tolerance: float = NEIGHBOUR_TOLERANCE) -> np.ndarray:
    """positions: (R, 2) tile centres, (lat, lon) degrees (kind "latlon") or (east, north) metres ("xy"); extent_m:
    (R, 2) the (height, width) metres each tile covers -> (R, 3, 3) the index of the tile whose centre lies half a
    tile north / south and east / west of each tile's (row r, column c: (1 - r) half-heights north, (c - 1)
    half-widths east), -1 where no tile's centre lies within `tolerance` of a half-tile of that point."""
    from scipy.spatial import cKDTree

    positions = np.asarray(positions, np.float64).reshape(-1, 2)
    extent = np.broadcast_to(np.asarray(extent_m, np.float64), positions.shape)
    if kind not in ("latlon", "xy"):
        raise ValueError(f"tile_neighbours: positions are 'latlon' or 'xy', got {kind!r}")
    if not (np.isfinite(positions).all() and np.isfinite(extent).all() and (extent > 0).all()):
        raise ValueError("tile_neighbours needs every tile's position and a positive ground extent; some are "
                         "missing or not finite (a margin needs the tiles' positions and metres per pixel)")
    if kind == "latlon":  # points on the unit sphere: a chord of d / R for d metres apart at these distances
        def points(north, east):
            lat = positions[:, 0] + np.degrees(north / EARTH_RADIUS_M)
            lon = positions[:, 1] + np.degrees(east / (EARTH_RADIUS_M * np.cos(np.radians(positions[:, 0]))))
            return _unit_vectors(np.column_stack([lat, lon]))
        unit = EARTH_RADIUS_M
    else:
        def points(north, east):
            return positions + np.column_stack([east, north])
        unit = 1.0
    tree = cKDTree(points(np.zeros(len(positions)), np.zeros(len(positions))))
    reach = tolerance * np.minimum(extent[:, 0], extent[:, 1]) / 2 / unit
    out = np.full((len(positions), 3, 3), -1, np.int64)
    out[:, 1, 1] = np.arange(len(positions))
    for r in range(3):
        for c in range(3):
            if (r, c) != (1, 1):
                distance, index = tree.query(points((1 - r) * extent[:, 0] / 2, (c - 1) * extent[:, 1] / 2))
                out[:, r, c] = np.where(distance <= reach, index, -1)
    return out


def margin_pixels(side: int, margin: float) -> int:
    """The pixels beyond each edge of a tile read `side` pixels across with `margin` of its side around it: even,
    so that the refiner's half-resolution maps have a whole number of margin cells."""
    return 2 * int(round(margin * side / 2))


def stitched_side(side: int, margin: float) -> int:
    """The pixels across a tile read `side` pixels across with `margin` of its side around it (at_side's output)."""
    return side + 2 * margin_pixels(side, margin)


def stitched(tile: int, neighbourhood: np.ndarray, read: Callable[[int], np.ndarray | None],
             margin: float) -> np.ndarray | None:
    """Tile `tile` with `margin` of its side (at most 0.5) of ground beyond each edge: read(i) gives tile i's image
    (H x W x 3 uint8; a neighbour of another size is resized to the tile's), or None where it cannot be read (the
    tile's own: then None is returned; a neighbour's: its margin is left uncovered); neighbourhood: its (3, 3) row
    of tile_neighbours. -> (H + 2 mH) x (W + 2 mW) x 4 uint8 (mH = round(margin H)): the RGB image, then 255 where a
    tile covers the pixel and 0 where none does (RGB 0 there). The tile's own pixels are its own; the margin comes
    from the neighbours, each laid half a tile off."""
    if not 0.0 <= margin <= 0.5:
        raise ValueError(f"stitched: a margin of {margin} of the tile's side; the tiles beside it cover at most half "
                         "a tile beyond each edge (0 to 0.5)")
    image = read(tile)
    if image is None:
        return None
    h, w = image.shape[:2]
    mh, mw = int(round(margin * h)), int(round(margin * w))
    canvas = np.zeros((h + 2 * mh, w + 2 * mw, 4), np.uint8)
    for r in range(3):
        for c in range(3):
            index = int(neighbourhood[r, c])
            if (r, c) == (1, 1) or index < 0:
                continue
            other = read(index)
            if other is None:
                continue
            if other.shape[:2] != (h, w):
                other = cv2.resize(other, (w, h), interpolation=cv2.INTER_AREA)
            top, left = mh + (r - 1) * (h // 2), mw + (c - 1) * (w // 2)
            y0, x0 = max(top, 0), max(left, 0)
            y1, x1 = min(top + h, canvas.shape[0]), min(left + w, canvas.shape[1])
            if y1 > y0 and x1 > x0:
                canvas[y0:y1, x0:x1, :3] = other[y0 - top:y1 - top, x0 - left:x1 - left]
                canvas[y0:y1, x0:x1, 3] = 255
    canvas[mh:mh + h, mw:mw + w, :3] = image
    canvas[mh:mh + h, mw:mw + w, 3] = 255
    return canvas


@dataclass
class TileFiles:
    """read(i) for a list of tile files: a plain object rather than a closure, so a data loader's workers can be
    handed a TileContext under any start method."""

    paths: list

    def __call__(self, index: int) -> np.ndarray:
        return read_rgb(self.paths[index])


@dataclass
class TileContext:
    """The tiles of one gallery read with a margin: read(i) tile i's image, neighbours their tile_neighbours."""

    read: Callable[[int], np.ndarray]
    neighbours: np.ndarray
    margin: float

    @classmethod
    def of(cls, split, margin: float) -> "TileContext | None":
        """The context of a RetrievalSplit's references (None at margin 0): their positions and extent place them."""
        if not margin:
            return None
        if split.reference_latlon is None or split.reference_extent_m is None:
            raise ValueError(f"{split.name}: refiner.margin reads each tile with the tiles beside it, which needs the "
                             "tiles' positions and metres per pixel; this split has none (use refiner.margin=0)")
        return cls(TileFiles(list(split.references)), tile_neighbours(split.reference_latlon,
                                                                     split.reference_extent_m), margin)

    @classmethod
    def of_gallery(cls, read: Callable[[int], np.ndarray | None], positions, extent_m, kind: str,
                   margin: float) -> "TileContext":
        """The context of a saved gallery's tiles: read(row) their images (None where not there), positions and
        extent as its places give them (kind "latlon" or "xy")."""
        return cls(read, tile_neighbours(positions, extent_m, kind), margin)

    def image(self, tile: int, side: int | None = None) -> np.ndarray | None:
        """Tile `tile` and its margin (stitched), at stitched_side(side) pixels across where `side` is
        given (at_side), else at the tiles' own resolution; None where the tile itself cannot be read."""
        canvas = stitched(tile, self.neighbours[tile], self.read, self.margin)
        return canvas if side is None or canvas is None else at_side(canvas, side, self.margin)


def at_side(canvas: np.ndarray, side: int, margin: float) -> np.ndarray:
    """A stitched tile (H' x W' x 4) at stitched_side(side) pixels across: the colours by area, a pixel
    covered only where every pixel it is drawn from is."""
    size = stitched_side(side, margin)
    rgb = cv2.resize(np.ascontiguousarray(canvas[..., :3]), (size, size), interpolation=cv2.INTER_AREA)
    covered = cv2.resize(np.ascontiguousarray(canvas[..., 3]), (size, size), interpolation=cv2.INTER_AREA)
    return np.dstack([rgb, np.where(covered == 255, 255, 0).astype(np.uint8)])


def tile_size(canvas_size: int, margin: float) -> int:
    """The side of the tile inside a stitched canvas canvas_size pixels across: the h with h + 2 round(margin h) =
    canvas_size (h + 2 round(margin h) grows by at least 1 with h, so there is at most one)."""
    guess = int(round(canvas_size / (1 + 2 * margin)))
    for h in (guess, guess - 1, guess + 1):
        if h + 2 * int(round(margin * h)) == canvas_size:
            return h
    raise ValueError(f"tile_size: no tile read with a margin of {margin} makes a canvas {canvas_size} pixels across")


def own_pixels(canvas: np.ndarray, margin: float) -> np.ndarray:
    """The tile's own image (H x W x 3) inside a stitched canvas: the pixels `stitched` copied from the tile."""
    h, w = (tile_size(n, margin) for n in canvas.shape[:2])
    top, left = (canvas.shape[0] - h) // 2, (canvas.shape[1] - w) // 2
    return np.ascontiguousarray(canvas[top:top + h, left:left + w, :3])
