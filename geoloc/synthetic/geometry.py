"""The ground geometry of a rendered dataset's aerial tiles, read from its marker: what a reader needs to put the
camera in metres on a tile (RetrievalSplit.reference_size_px / reference_metres_per_px).

- cvusa, cvact: one tile per place, centred on the camera: the centred square of round(tile_m / cell_m) world cells
  (aerial.tile_slice) drawn at aerial_size pixels;
- vigor: the city grid's tiles, tile_m rounded to a multiple of 4 cells (tiles.TileGrid.fit), at aerial_size pixels.
The other layouts have no tile that holds a street camera: None.
"""
from __future__ import annotations

import json
from pathlib import Path

from .world_config import OPTIONS, SynthConfig
from .generate import MARKER
from .tiles import TileGrid


def tile_geometry(root) -> tuple[int, float] | None:
    """(tile side in pixels, ground metres per pixel) of the synthetic dataset at `root`, or None when root holds no
    synthetic dataset of a layout with camera tiles (a real dataset). A marker that is not complete (a render stopped
    part-way) is refused: read as a release, the tree would get the release's frame and scale in silence."""
    path = Path(root) / MARKER
    if not path.is_file():
        return None
    try:
        marker = json.loads(path.read_text())
        cfg = SynthConfig(**marker["config"])
        layout = marker["layout"]
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path} is not a readable geoloc synthetic marker ({err}); render the dataset again "
                         "into an empty folder") from err
    if not marker.get("complete"):
        raise ValueError(unfinished_render(root, f"its {MARKER} says the render did not complete"))
    return layout_geometry(layout, cfg, marker.get("options"))


def unfinished_render(root, why: str) -> str:
    """The refusal of a synthetic tree whose render did not finish, saying `why` it is one and what to do."""
    return (f"{root} is an unfinished geoloc synthetic render ({why}); render it again into an empty folder (delete "
            "this one), or let the render that is writing it finish")


def layout_geometry(layout: str, cfg: SynthConfig, options: dict | None = None) -> tuple[int, float] | None:
    """(tile side in pixels, metres per pixel) of `layout` rendered with `cfg` (and the layout's options)."""
    if layout in ("cvusa", "cvact"):
        cells = int(round(cfg.tile_m / cfg.cell_m))
        return cfg.aerial_size, cells * cfg.cell_m / cfg.aerial_size
    if layout == "vigor":
        grid = TileGrid.fit(OPTIONS["vigor"](**(options or {})).grid, cfg.tile_m, cfg.cell_m)
        return cfg.aerial_size, grid.tile_m / cfg.aerial_size
    return None
