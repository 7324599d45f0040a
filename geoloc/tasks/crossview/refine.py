"""Fine-grained localisation in the cross-view task: the refiner's config, its training items and its metrics.

A run refines when its config has a `refiner` section (conf/refiner/<name>.yaml): the refiner's own keys go to its
registered factory (geoloc/models/refiners/), and the keys of RefineConfig say how it is trained and tested. With no
`refiner` section nothing here runs and the task is retrieval alone.

Positions are tile fractions (row, col) as geoloc.models.refiners.Refinement gives them; the truth is the split's
query_tile_px over reference_size_px (VIGOR's offsets, unrounded where the synthetic tree writes them), the tile
centre for one-to-one data (CVUSA, CVACT: the camera is at the centre, only the heading is to find).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields, replace

import numpy as np
import torch

import geoloc.models.refiners  # noqa: F401  (declares the refiner kind, registers the built-ins)
from geoloc import registry
from geoloc.config import checked
from geoloc.data.geo import distance_m, offset_to_latlon
from geoloc.data.io import read_rgb
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.fine_error import (E2E_KEYS, FINE_HEADING_KEYS, FINE_KEYS, e2e_summary, fine_summary,
                                    heading_summary)
from geoloc.eval.scoring import top_k
from geoloc.tasks.crossview.transforms import align_query, flip_rotate, resize, to_tensor
from geoloc.tasks.crossview.views import EVAL_HEADING_SEED, candidate_headings, circular_error_deg, crop_view

STAGES = ("refine", "joint")
RADIUS_M = 5.0  # the refined answer's confidence is P(error <= RADIUS_M) (confidence.py's "within_5m")
log = logging.getLogger(__name__)


@dataclass
class RefineConfig:
    """How the refiner trains and is tested (the `refiner` section's keys beside the refiner's own)."""

    stage: str = "refine"  # refine: only the refiner trains (from init_from=RUN/last.pt); joint: with retrieval
    weight: float = 1.0  # joint: the refiner's loss weight beside the retrieval loss
    orientation_noise_deg: float = 0.0  # the query's heading is U(-X, X) off north (CCVPE's ori_noise); 0: known
    semi_positives: bool = False  # train on the semi-positive tiles that hold the panorama too (CCVPE)
    size: int = 0  # the side in pixels the refiner reads the aligned query and the tile at; 0: dataset.aerial_size

    def __post_init__(self):
        if self.stage not in STAGES:
            raise ValueError(f"refiner.stage must be one of {STAGES}, got {self.stage!r}")
        if not 0.0 <= self.orientation_noise_deg <= 180.0:
            raise ValueError(f"refiner.orientation_noise_deg must lie in [0, 180], got {self.orientation_noise_deg}")
        if self.weight <= 0 or self.size < 0 or self.size % 2:
            raise ValueError(f"refiner.weight must be > 0 and refiner.size an even number >= 0 (0: "
                             f"dataset.aerial_size); got weight={self.weight}, size={self.size}")

    def side(self, aerial_size: int) -> int:
        return self.size or aerial_size

    def candidates(self, heading_bins: int) -> torch.Tensor:
        """(K,) the headings tried: north alone when known; otherwise the bins 360 k / K within the prior +-X
        (every bin at X = 180)."""
        if self.orientation_noise_deg == 0:
            return torch.zeros(1)
        bins = torch.from_numpy(candidate_headings(heading_bins)).float()
        if self.orientation_noise_deg >= 180.0:
            return bins
        off = (bins + 180.0) % 360.0 - 180.0
        return bins[off.abs() <= self.orientation_noise_deg + 180.0 / heading_bins]


REFINE_KEYS = tuple(f.name for f in fields(RefineConfig))


def parse_refiner(section) -> tuple[RefineConfig | None, dict | None]:
    """(RefineConfig, the refiner's own section: name, module and the factory's keys, checked) or (None, None)."""
    if not section:
        return None, None
    params = dict(section)
    refine = checked({k: v for k, v in params.items() if k in REFINE_KEYS}, RefineConfig, "refiner")
    own = {k: v for k, v in params.items() if k not in REFINE_KEYS}
    registry.check("refiner", own)
    return refine, own


def refine_nodes() -> dict[str, dict]:
    """`refiner/<name>` schema nodes: RefineConfig's keys, then the factory's (as datasets do with their shared
    keys)."""
    from geoloc.config import defaults_of

    shared = defaults_of(RefineConfig)
    return {f"refiner/{name}": {**shared, **registry.with_defaults("refiner", {"name": name})}
            for name in registry.names("refiner")}


# ---- items --------------------------------------------------------------------------------------------------
def eval_offset(index: int, noise_deg: float) -> float:
    """The fixed heading of test query `index` under orientation noise +-X: U(-X, X) from numpy's
    default_rng((EVAL_HEADING_SEED, index)), the draw views.eval_heading makes, so every run meets the same ones."""
    if noise_deg == 0:
        return 0.0
    u = np.random.default_rng((EVAL_HEADING_SEED, int(index))).uniform(0.0, 1.0)
    return float((2.0 * u - 1.0) * noise_deg)


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


def refine_item(split: RetrievalSplit, index: int, street: np.ndarray, cfg, refine: RefineConfig,
                rng: np.random.Generator | None) -> dict:
    """A training (rng given) or test item for the refiner: the query seen at a heading off north (drawn, or fixed
    per query for tests), the tile (the positive, or with semi_positives any tile holding the query), the truth.

    -> {"street": the view (H x W x 3, for the retrieval inputs), "aerial": the tile as turned, "refine_query",
    "refine_reference": 3 x s x s, "tile_px": (2,) tile fraction, "refine_heading": degrees in [0, 360)}."""
    tiles = [int(split.positives[index])]
    if refine.semi_positives and split.semi_positives is not None and rng is not None:
        tiles += [int(t) for t in split.semi_positives[index] if t >= 0]
    tile = tiles[int(rng.integers(len(tiles)))] if len(tiles) > 1 else tiles[0]
    frac = truth_fraction(split, index, tile)
    aerial = read_rgb(split.references[tile])
    if rng is not None and cfg.joint_flip_rotate:
        turns, flip = int(rng.integers(4)), bool(rng.integers(2))
        street, aerial = flip_rotate(street, aerial, turns, flip)
        frac = turned_fraction(frac, turns, flip)
    noise = refine.orientation_noise_deg
    offset = (float(rng.uniform(-noise, noise)) if noise > 0 else 0.0) if rng is not None else eval_offset(index, noise)
    view = crop_view(street, 360.0, offset) if offset else street
    side = refine.side(cfg.aerial_size)
    small = replace(cfg, aerial_size=side)
    return {"street": view, "aerial": aerial,
            "refine_query": to_tensor(align_query(view, small, split.query_view)),
            "refine_reference": to_tensor(resize(aerial, (side, side))),
            "tile_px": torch.tensor(frac, dtype=torch.float32), "refine_heading": offset % 360.0}


# ---- metrics ------------------------------------------------------------------------------------------------
def fine_plan(split: RetrievalSplit, refine: RefineConfig) -> list:
    """The key sets refinement reports on `split`: metres where the tiles' scale is known, the heading when it is
    unknown, end to end where the split has positions and is not one-to-one."""
    plan = [FINE_KEYS] if split.reference_metres_per_px is not None else []
    if refine.orientation_noise_deg > 0:
        plan.append(FINE_HEADING_KEYS)
    if split.positions()[0] is not None and split.reference_metres_per_px is not None and not split.one_to_one:
        plan.append(E2E_KEYS)
    return plan


@torch.no_grad()
def refined(refiner, query_maps: torch.Tensor, reference_maps: torch.Tensor, tiles: torch.Tensor,
            candidates: torch.Tensor, chunk: int = 64,
            extent_m: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Each query's map matched against reference map tiles[i]: ((Q, 2) tile fractions, (Q,) headings, and with
    extent_m ((Q, 2) metres each query's tile covers) the (Q,) probability mass within RADIUS_M of each position,
    the refiner's own score that a calibrator maps to P(error <= RADIUS_M); else None)."""
    positions, headings, masses = [], [], []
    for start in range(0, query_maps.shape[0], chunk):
        part = slice(start, start + chunk)
        out = refiner.match(query_maps[part], reference_maps[tiles[part]], candidates)
        positions.append(out.position().float().cpu())
        headings.append(out.heading().float().cpu())
        if extent_m is not None:
            extent = torch.as_tensor(np.asarray(extent_m[part], np.float64), dtype=torch.float32)
            masses.append(out.mass_within(RADIUS_M, extent.to(query_maps.device)).float().cpu())
    return torch.cat(positions), torch.cat(headings), torch.cat(masses) if masses else None


def fine_metrics(refiner, split: RetrievalSplit, refine: RefineConfig, candidates: torch.Tensor,
                 query_maps: torch.Tensor, reference_maps: torch.Tensor, true_heading: torch.Tensor,
                 query_descriptors: torch.Tensor | None = None,
                 reference_descriptors: torch.Tensor | None = None) -> dict[str, float]:
    """fine_plan(split)'s metrics: each query refined in its positive tile (the fine-grained protocol), and in its
    top-1 retrieved tile (end to end: the tile centre's position plus the refined offset, against the query's)."""
    out: dict[str, float] = {}
    plan = fine_plan(split, refine)
    positives = torch.from_numpy(split.positives)
    position, heading, _ = refined(refiner, query_maps, reference_maps, positives, candidates)
    if FINE_KEYS in plan:
        out.update(fine_summary(positive_errors_m(position.numpy(), split)[shown_queries(split)]))
    if FINE_HEADING_KEYS in plan:
        out.update(heading_summary(circular_error_deg(heading.numpy(), true_heading.cpu().numpy())))
    if E2E_KEYS in plan:
        top1 = top_k(query_descriptors, reference_descriptors, 1)[1][:, 0].cpu()
        e2e_position, _, _ = refined(refiner, query_maps, reference_maps, top1, candidates)
        out.update(e2e_summary(e2e_errors_m(e2e_position.numpy(), top1.numpy(), split)))
    return out


def fine_answers(refiner, split: RetrievalSplit, candidates: torch.Tensor, query_maps: torch.Tensor,
                 reference_maps: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Each query a tile shows (`shown_queries`) refined in its positive tile: ((Q',) the probability mass within
    RADIUS_M of its position, (Q',) its metre error): what the "within_5m" confidence is fitted on and scored
    against (confidence.py)."""
    if split.reference_metres_per_px is None:
        raise ValueError(f"{split.name}: its tiles have no metres per pixel, so a metre error has no meaning")
    positives = torch.from_numpy(split.positives)
    extent = split.reference_extent_m[split.positives]
    position, _, mass = refined(refiner, query_maps, reference_maps, positives, candidates, extent_m=extent)
    shown = shown_queries(split)
    return mass.double().numpy()[shown], positive_errors_m(position.numpy(), split)[shown]


def shown_queries(split: RetrievalSplit) -> np.ndarray:
    """(Q,) bool: the queries whose position in their positive tile is known. A test query that no tile shows
    (own data under the radius rule keeps it, its query_tile_px NaN) has no fine-grained error: the fine-grained
    metrics skip it, and a warning says how many they skip."""
    if split.query_tile_px is None:
        return np.ones(split.num_queries, bool)
    shown = ~np.isnan(split.query_tile_px).any(axis=1)
    if not shown.all():
        log.warning("%s: %d of %d queries lie in no tile, so their position in a tile is unknown: the fine-grained "
                    "metrics (fine_*) skip them", split.name, int((~shown).sum()), split.num_queries)
    return shown


def positive_errors_m(position: np.ndarray, split: RetrievalSplit) -> np.ndarray:
    """(Q,) metres between each query's (Q, 2) refined tile fraction in its positive tile and the truth (NaN where
    the truth is unknown: `shown_queries`)."""
    truth = np.stack([truth_fraction(split, i, int(t)) for i, t in enumerate(split.positives)])
    return fraction_error_m(position, truth, split, split.positives)


def fraction_error_m(estimate: np.ndarray, truth: np.ndarray, split: RetrievalSplit, tiles) -> np.ndarray:
    """(Q,) metres between two (Q, 2) tile fractions of tiles[i]: pixels of the tile times its metres per pixel."""
    extent = split.reference_extent_m[np.asarray(tiles)]  # (Q, 2) height, width metres
    return np.linalg.norm((estimate - truth) * extent, axis=1)


def offset_m(fraction: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """(Q, 2) (east, north) metres of tile fractions from the tile centre (rows grow south, columns east)."""
    return np.column_stack([(fraction[:, 1] - 0.5) * extent[:, 1], (0.5 - fraction[:, 0]) * extent[:, 0]])


def refined_positions(fraction: np.ndarray, tiles: np.ndarray, split: RetrievalSplit) -> tuple[str, np.ndarray]:
    """(kind, (Q, 2) positions) of tile fractions in tiles[i]: (lat, lon) degrees or (x, y) metres, the tile
    centre's position moved by the refined offset."""
    kind, _, references = split.positions()
    east_north = offset_m(fraction, split.reference_extent_m[tiles])
    if kind == "latlon":
        return kind, np.stack([offset_to_latlon(references[t], e, n) for t, (e, n) in zip(tiles, east_north)])
    return kind, references[tiles] + east_north


def e2e_errors_m(fraction: np.ndarray, top1: np.ndarray, split: RetrievalSplit) -> np.ndarray:
    kind, queries, _ = split.positions()
    kind, found = refined_positions(fraction, top1, split)
    return distance_m(queries, found, kind)
