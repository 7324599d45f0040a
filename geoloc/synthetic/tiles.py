"""The vigor layout's satellite grid: square tiles whose centres lie half a tile apart in both directions.

Every point between the outermost tile centres then lies inside exactly four tiles (VIGOR's terms): the
*positive*, whose central quarter (the middle half of each side) holds it, and three *semi-positives* that hold
it off centre. Metres are x east, y north from the grid's centre; tile (ix, iy) counts ix from the west and iy from
the north, and is number iy * n + ix in the city's satellite list.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TileGrid:
    n: int  # tiles per side
    tile_cells: int  # tile side in world cells, a multiple of 4, so every tile centre is a cell corner
    cell: float  # metres per world cell

    def __post_init__(self):
        if self.n < 2 or self.tile_cells < 4 or self.tile_cells % 4:
            raise ValueError(f"a tile grid needs n >= 2 and tile_cells a positive multiple of 4, got {self}")

    @classmethod
    def fit(cls, n: int, tile_m: float, cell: float) -> "TileGrid":
        """The grid whose tile side is tile_m rounded to a multiple of 4 cells."""
        return cls(n, 4 * max(1, int(round(tile_m / cell / 4))), cell)

    @property
    def tile_m(self) -> float:
        return self.tile_cells * self.cell

    @property
    def step_m(self) -> float:
        return self.tile_m / 2

    @property
    def half_span_m(self) -> float:
        """Points with |x|, |y| <= this lie inside four tiles."""
        return (self.n - 1) / 2 * self.step_m

    def centre(self, ix: int, iy: int) -> tuple[float, float]:
        """(east, north) metres of tile (ix, iy)'s centre."""
        return (ix - (self.n - 1) / 2) * self.step_m, ((self.n - 1) / 2 - iy) * self.step_m

    def number(self, ix: int, iy: int) -> int:
        return iy * self.n + ix

    def tiles_holding(self, east: float, north: float) -> list[tuple[int, int]]:
        """[positive, semi-positive across east-west, across north-south, diagonal] as (ix, iy)."""
        if max(abs(east), abs(north)) > self.half_span_m + 1e-9:
            raise ValueError(f"({east:.2f}, {north:.2f}) m is outside the grid's interior "
                             f"(|x|, |y| <= {self.half_span_m:.2f} m): fewer than four tiles hold it")
        last = self.n - 1
        ix = int(np.clip(np.round(east / self.step_m + last / 2), 0, last))
        iy = int(np.clip(np.round(last / 2 - north / self.step_m), 0, last))
        ce, cn = self.centre(ix, iy)
        jx = _neighbour(ix, 1 if east >= ce else -1, last)
        jy = _neighbour(iy, -1 if north >= cn else 1, last)  # north is towards smaller iy
        return [(ix, iy), (jx, iy), (ix, jy), (jx, jy)]

    def cells(self, ix: int, iy: int, world_n: int) -> tuple[slice, slice]:
        """(rows, cols) of tile (ix, iy) in a world of world_n x world_n cells centred on the grid."""
        ce, cn = self.centre(ix, iy)
        col = world_n // 2 + int(round(ce / self.cell)) - self.tile_cells // 2
        row = world_n // 2 - int(round(cn / self.cell)) - self.tile_cells // 2
        if min(row, col) < 0 or max(row, col) + self.tile_cells > world_n:
            raise ValueError(f"tile ({ix}, {iy}) does not fit a world of {world_n} cells")
        return slice(row, row + self.tile_cells), slice(col, col + self.tile_cells)


def _neighbour(index: int, step: int, last: int) -> int:
    """The neighbour on the point's side; on a tile's centre line at the grid's edge, the one that exists."""
    return index + step if 0 <= index + step <= last else index - step
