"""The density of weighted particles in the plane, as the weight in the 3 x 3 block of square cells around a point.

A box-kernel estimate on a fixed lattice of cells (side `cell_m`): the density anywhere in a cell is the weight of
the particles in that cell and its eight neighbours over the block's area (9 cell_m^2). It is what the particle
filter's 95% region and its main mode are read from. Only occupied cells are stored (sorted integer keys), so a
posterior spread over a whole city costs memory in particles, not in city area; one look-up is 9 binary searches.
"""

from __future__ import annotations

import numpy as np

_OFFSET = 1 << 30  # cell indices are shifted to be non-negative, then packed two to an int64 key
_NEIGHBOURS = np.array([(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1)], np.int64)


class CellDensity:
    """points (N, 2) metres with weights (N,) summing to one; cell_m: the side of a cell in metres."""

    def __init__(self, points, weights, cell_m: float):
        if cell_m <= 0:
            raise ValueError(f"cell_m must be positive, got {cell_m}")
        self.cell_m = float(cell_m)
        keys = _keys(self.cells(points))
        self.keys, inverse = np.unique(keys, return_inverse=True)
        self.inverse = inverse.ravel()  # each point's occupied cell
        self.mass = np.bincount(self.inverse, np.asarray(weights, np.float64), minlength=len(self.keys))

    def cells(self, points) -> np.ndarray:
        """(N, 2) int64 lattice indices of (N, 2) points."""
        cells = np.floor(np.asarray(points, np.float64) / self.cell_m)
        if np.abs(cells).max(initial=0) >= _OFFSET:
            raise ValueError(f"points lie more than {_OFFSET} cells of {self.cell_m} m from the origin: use local "
                             "metres around the gallery")
        return cells.astype(np.int64)

    def block_mass(self, cells) -> np.ndarray:
        """(N,) the weight in the 3 x 3 block of cells around each of (N, 2) cell indices."""
        out = np.zeros(len(cells))
        for offset in _NEIGHBOURS:
            key = _keys(cells + offset)
            at = np.minimum(np.searchsorted(self.keys, key), len(self.keys) - 1)
            out += np.where(self.keys[at] == key, self.mass[at], 0.0)
        return out

    def at(self, points) -> np.ndarray:
        """(N,) the density (per square metre) at (N, 2) points."""
        return self.block_mass(self.cells(points)) / (9 * self.cell_m ** 2)

    def at_own_points(self) -> np.ndarray:
        """(N,) the density at the points it was built from: one look-up per occupied cell, not per point."""
        return (self.block_mass(self.occupied_cells()) / (9 * self.cell_m ** 2))[self.inverse]

    def occupied_cells(self) -> np.ndarray:
        """(M, 2) the cells holding a point."""
        return np.stack([self.keys // (2 * _OFFSET), self.keys % (2 * _OFFSET)], 1) - _OFFSET

    def near_cells(self) -> np.ndarray:
        """(M, 2) every cell whose density is above zero: the occupied cells and their neighbours."""
        around = (self.occupied_cells()[:, None, :] + _NEIGHBOURS[None]).reshape(-1, 2)
        return np.unique(around, axis=0)


def _keys(cells: np.ndarray) -> np.ndarray:
    return (cells[:, 0] + _OFFSET) * (2 * _OFFSET) + (cells[:, 1] + _OFFSET)
