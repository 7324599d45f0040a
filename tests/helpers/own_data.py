"""Own-data folders (dataset=folder) on disk: random images with stated positions."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from geoloc.data.geo import offset_to_latlon

ORIGIN = (48.8566, 2.3522)  # where the stand-in positions are laid out (lat, lon)


def write_folder(root: Path, tile_east_north, query_east_north, aerial: int = 64, pano=(32, 128), seed: int = 0,
                 system: str = "latlon", query_names=None, origin=ORIGIN) -> Path:
    """ROOT/tiles/tNNN.png and ROOT/queries/qNNN.png of random pixels, with tiles.csv and queries.csv giving the
    (east, north) metres around `origin` as lat,lon (system "latlon") or as east_m,north_m ("xy")."""
    rng = np.random.default_rng(seed)
    for side, positions, shape, prefix in (("tiles", tile_east_north, (aerial, aerial), "t"),
                                           ("queries", query_east_north, tuple(pano), "q")):
        (root / side).mkdir(parents=True, exist_ok=True)
        names = [f"{prefix}{i:03d}.png" for i in range(len(positions))]
        if side == "queries" and query_names is not None:
            names = list(query_names)
        for name in names:
            cv2.imwrite(str(root / side / name), rng.integers(0, 255, (*shape, 3), np.uint8))
        (root / f"{side}.csv").write_text(positions_csv(names, positions, system, origin))
    return root


def positions_csv(names, east_north, system: str = "latlon", origin=ORIGIN) -> str:
    east_north = np.asarray(east_north, np.float64).reshape(-1, 2)
    if system == "xy":
        return "image,east_m,north_m\n" + "".join(f"{n},{e:.3f},{v:.3f}\n" for n, (e, v) in zip(names, east_north))
    latlon = offset_to_latlon(origin, east_north[:, 0], east_north[:, 1])
    return "image,lat,lon\n" + "".join(f"{n},{a:.8f},{b:.8f}\n" for n, (a, b) in zip(names, latlon))


def grid(n_east: int, n_north: int, step_m: float) -> np.ndarray:
    """(n_east * n_north, 2) (east, north) metres of a grid, east fastest."""
    east, north = np.meshgrid(np.arange(n_east) * step_m, np.arange(n_north) * step_m)
    return np.column_stack([east.ravel(), north.ravel()])
