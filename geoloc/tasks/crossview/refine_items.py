"""The refiner's items: a query and the tile it is matched in, as training and testing read them (refine.py holds the
refiner's config and its metrics).

A pair is a query and a tile that holds it: its positive, or with refiner.semi_positives any semi-positive whose truth
lies inside it (tile_pairs). The truth is the query's position as a tile fraction (truth_fraction), turned with the
tile by the joint flip / rotation augmentation (turned_fraction). A test query is seen at a fixed heading off north
under orientation noise (eval_offset), so every run meets the same ones. With refiner.margin the tile is read with the
ground around it (geoloc/data/tile_context.py), 4 channels (tile_input).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from geoloc.data.io import read_rgb
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.data.tile_context import TileContext, at_side, own_pixels
from geoloc.tasks.crossview.transforms import align_query, flip_rotate, resize, to_tensor, turned_tile
from geoloc.tasks.crossview.views import EVAL_HEADING_SEED, crop_view


def eval_offset(index: int, noise_deg: float) -> float:
    """The fixed heading of test query `index` under orientation noise +-X: U(-X, X) from numpy's
    default_rng((EVAL_HEADING_SEED, index)), the draw views.eval_heading makes, so every run meets the same ones."""
    if noise_deg == 0:
        return 0.0
    u = np.random.default_rng((EVAL_HEADING_SEED, int(index))).uniform(0.0, 1.0)
    return float((2.0 * u - 1.0) * noise_deg)


def tile_pairs(split: RetrievalSplit, whole_tile: bool, queries=None) -> tuple[np.ndarray, np.ndarray]:
    """((P,) query rows, (P,) tile rows) of the pairs of `queries` (default all) with a tile that holds them: the
    positive, and with `whole_tile` each semi-positive whose truth lies inside it (RetrievalSplit.semi_inside)."""
    rows = np.arange(split.num_queries) if queries is None else np.asarray(queries, np.int64)
    inside = split.semi_inside() if whole_tile else None
    if inside is None:
        return rows, split.positives[rows]
    keep = np.column_stack([np.ones(len(rows), bool), inside[rows]])
    tiles = np.column_stack([split.positives[rows], split.semi_positives[rows]])
    return np.broadcast_to(rows[:, None], tiles.shape)[keep], tiles[keep]


def truth_fraction(split: RetrievalSplit, index: int, tile: int) -> np.ndarray:
    """(row, col) tile fraction of query `index` in reference `tile` (its positive or a semi-positive)."""
    if split.query_tile_px is None:
        return np.array([0.5, 0.5])
    size = split.reference_size_px[tile].astype(np.float64)
    if tile == split.positives[index]:
        return split.query_tile_px[index] / size
    j = int(np.flatnonzero(split.semi_positives[index] == tile)[0])
    return split.query_semi_tile_px[index, j] / size


def turned_fraction(frac: np.ndarray, quarter_turns: int, flip: bool) -> np.ndarray:
    """A tile fraction after transforms.flip_rotate's east-west mirror, then quarter turns clockwise."""
    row, col = float(frac[0]), float(frac[1])
    if flip:
        col = 1.0 - col
    for _ in range(quarter_turns):
        row, col = col, 1.0 - row
    return np.array([row, col])


def refine_item(split: RetrievalSplit, index: int, street: np.ndarray, cfg, refine,
                rng: np.random.Generator | None, context: TileContext | None = None) -> dict:
    """A training (rng given) or test item for the refiner (`refine`: its refine.RefineConfig): the query seen at a
    heading off north (drawn, or fixed per query for tests), the tile (the positive, or with semi_positives any tile
    holding the query), the truth.

    -> {"street": the view (H x W x 3, for the retrieval inputs), "aerial": the tile as turned, "refine_query",
    "refine_reference": 3 x s x s (with `context`, refine.margin's TileContext: 4 x s' x s', the tile and its
    margin, tile_input), "tile_px": (2,) tile fraction, "refine_heading": degrees in [0, 360),
    "refine_extent_m": (2,) metres the tile covers (NaN where the split has no scale)}."""
    _, tiles = tile_pairs(split, refine.semi_positives and rng is not None, [index])
    tile = int(tiles[int(rng.integers(len(tiles)))]) if len(tiles) > 1 else int(tiles[0])
    frac = truth_fraction(split, index, tile)
    side = refine.side(cfg.aerial_size)
    if context is None:
        aerial, wide = read_rgb(split.references[tile]), None
    else:  # the tile is decoded once: the retrieval inputs take its own pixels, the refiner the canvas at its side
        canvas = context.image(tile)
        aerial, wide = own_pixels(canvas, context.margin), at_side(canvas, side, context.margin)
    if rng is not None and cfg.joint_flip_rotate:
        turns, flip = int(rng.integers(4)), bool(rng.integers(2))
        street, aerial = flip_rotate(street, aerial, turns, flip)
        wide = None if wide is None else turned_tile(wide, turns, flip)
        frac = turned_fraction(frac, turns, flip)
    extent = (np.full(2, np.nan) if split.reference_extent_m is None
              else split.reference_extent_m[tile].astype(np.float64))
    noise = refine.orientation_noise_deg
    offset = (float(rng.uniform(-noise, noise)) if noise > 0 else 0.0) if rng is not None else eval_offset(index, noise)
    view = crop_view(street, 360.0, offset) if offset else street
    small = replace(cfg, aerial_size=side)
    return {"street": view, "aerial": aerial,
            "refine_query": to_tensor(align_query(view, small, split.query_view)),
            "refine_reference": tile_input(aerial if wide is None else wide, side),
            "tile_px": torch.tensor(frac, dtype=torch.float32), "refine_heading": offset % 360.0,
            "refine_extent_m": torch.tensor(extent, dtype=torch.float32)}


def tile_input(tile: np.ndarray, side: int) -> torch.Tensor:
    """The refiner's reference input: a tile (H x W x 3 uint8) -> 3 x side x side, normalised as to_tensor; or a
    tile with its margin (TileContext.image: S x S x 4, already at its side) -> 4 x S x S, the RGB normalised and
    then 1 where imagery lies, 0 where none (CorrelationRefiner.encode_reference)."""
    if tile.shape[-1] == 3:
        return to_tensor(resize(tile, (side, side)))
    covered = torch.from_numpy(np.ascontiguousarray(tile[..., 3] == 255)).float()[None]
    return torch.cat([to_tensor(np.ascontiguousarray(tile[..., :3])), covered])
