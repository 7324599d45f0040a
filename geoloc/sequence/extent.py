"""Where the gallery lies: the box of its tiles in local metres, the support of the filter's uniform prior.

A route can only be localised to a place the gallery covers, so "anywhere" means anywhere in this box: the box of
the tile centres, padded by half a tile on each side so that it holds every tile whole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GalleryExtent:
    """The box east_min <= east <= east_max, north_min <= north <= north_max, in metres."""

    east_min: float
    east_max: float
    north_min: float
    north_max: float

    def __post_init__(self):
        if not (self.east_max > self.east_min and self.north_max > self.north_min):
            raise ValueError(f"a gallery extent needs east_max > east_min and north_max > north_min, got {self}")

    @classmethod
    def from_centres(cls, centres, tile_width_m: float) -> GalleryExtent:
        """The box of (N, 2) tile centres (east, north metres), padded by half a tile: every tile lies inside."""
        centres = np.asarray(centres, np.float64)
        if centres.ndim != 2 or centres.shape[1] != 2 or len(centres) == 0:
            raise ValueError(f"tile centres must be an N x 2 array of (east, north) metres, got shape {centres.shape}")
        if tile_width_m <= 0:
            raise ValueError(f"tile_width_m must be positive, got {tile_width_m}")
        half = tile_width_m / 2
        low, high = centres.min(0) - half, centres.max(0) + half
        return cls(float(low[0]), float(high[0]), float(low[1]), float(high[1]))

    @property
    def area_m2(self) -> float:
        return (self.east_max - self.east_min) * (self.north_max - self.north_min)

    def contains(self, points) -> np.ndarray:
        """(...,) bool: whether each (..., 2) point (east, north) lies in the box."""
        p = np.asarray(points, np.float64)
        return ((p[..., 0] >= self.east_min) & (p[..., 0] <= self.east_max)
                & (p[..., 1] >= self.north_min) & (p[..., 1] <= self.north_max))


@dataclass(frozen=True)
class RegionsExtent:
    """Several boxes far apart, as one support: a gallery of places that no route joins (cities laid side by side
    on the filter's plane, geoloc/apps/localize/route.py). Its area is the boxes' summed area, not that of the box
    around them, so the gaps between places weigh nothing in the uniform prior."""

    boxes: tuple[GalleryExtent, ...]

    def __init__(self, boxes):
        boxes = tuple(boxes)
        if not boxes:
            raise ValueError("a regions extent needs at least one box")
        object.__setattr__(self, "boxes", boxes)

    @property
    def area_m2(self) -> float:
        return float(sum(box.area_m2 for box in self.boxes))

    def contains(self, points) -> np.ndarray:
        """(...,) bool: whether each (..., 2) point (east, north) lies in one of the boxes."""
        return np.logical_or.reduce([box.contains(points) for box in self.boxes])

    def centres(self) -> np.ndarray:
        """(R, 2) each box's centre (east, north)."""
        return np.array([[(b.east_min + b.east_max) / 2, (b.north_min + b.north_max) / 2] for b in self.boxes])
