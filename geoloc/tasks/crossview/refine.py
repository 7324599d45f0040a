"""Fine-grained localisation in the cross-view task: the refiner's config and its metrics (its training and test items:
refine_items.py).

A run refines when its config has a `refiner` section (geoloc/conf/refiner/<name>.yaml): the refiner's own keys go to its
registered factory (geoloc/models/refiners/), and the keys of RefineConfig say how it is trained and tested. With no
`refiner` section nothing here runs and the task is retrieval alone.

Positions are tile fractions (row, col) as geoloc.models.refiners.Refinement gives them; the truth is the split's
query_tile_px over reference_size_px (VIGOR's offsets, unrounded where the synthetic tree writes them), the tile
centre for one-to-one data (CVUSA, CVACT: the camera is at the centre, only the heading is to find).

A query and a tile that holds it make a pair: its positive, and (with semi-positives, as VIGOR gives them) each
semi-positive whose truth lies inside it, so the truths of all pairs cover the whole tile (tile_pairs). Ground scale
is an input: with query_extent_m set, the query's map is drawn query_extent_m / (the tile's extent) times larger
before it is matched, so one refiner meets tiles of any ground extent at the scale it was trained at.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields
from typing import Callable, NamedTuple

import numpy as np
import torch

import geoloc.models.refiners  # noqa: F401  (declares the refiner kind, registers the built-ins)
from geoloc import registry
from geoloc.config import checked
from geoloc.data.geo import distance_m, offset_to_latlon
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.fine_error import (E2E_KEYS, FINE_HEADING_KEYS, FINE_KEYS, WHOLE_TILE_KEYS, e2e_summary,
                                    fine_summary, heading_summary, near_edge, whole_tile_summary)
from geoloc.eval.scoring import top_k
from geoloc.tasks.crossview.refine_items import tile_pairs, truth_fraction
from geoloc.tasks.crossview.views import candidate_headings, circular_error_deg

STAGES = ("refine", "joint")
METRE_LABELS = "metre_labels"  # the metrics' key that names the label set behind their metres (tile_labels)
RADIUS_M = 5.0  # the refined answer's confidence is P(error <= RADIUS_M) (geoloc/gallery/confidence.py's "within_5m")
log = logging.getLogger(__name__)


@dataclass
class RefineConfig:
    """How the refiner trains and is tested (the `refiner` section's keys beside the refiner's own)."""

    stage: str = "refine"  # refine: only the refiner trains (from init_from=RUN/last.pt); joint: with retrieval
    weight: float = 1.0  # joint: the refiner's loss weight beside the retrieval loss
    orientation_noise_deg: float = 0.0  # the query's heading is U(-X, X) off north (CCVPE's ori_noise); 0: known
    # train on every tile that holds the panorama (the semi-positives whose truth lies inside them too, as CCVPE):
    # truths over the whole tile instead of its central half
    semi_positives: bool = False
    size: int = 0  # the side in pixels the refiner reads the aligned query and the tile at; 0: dataset.aerial_size
    # the ground metres the aligned query stands for: a tile of extent E is matched with the query's map drawn
    # query_extent_m / E times larger (the ground scale as an input); 0: every tile as it is (docs/localisation.md
    # measures both)
    query_extent_m: float = 0.0
    # the answer is the peak of the position probability blurred by a Gaussian whose sigma is this share of the
    # tile's side (0.05: 3.6 m on a 73 m tile): the point with the most probability around it, which a narrow
    # spurious peak does not win; 0: the single most probable point, as the first refiners answered
    peak_smoothing: float = 0.0
    # the weight of a training truth near the tile's edge (fine_error.near_edge: within 0.1 of an edge) in the
    # refiner's loss, beside 1 for the others; 1: every truth alike
    edge_weight: float = 1.0
    # the tile is read with this share of its side of ground beyond each edge, cut from the half-overlapping tiles
    # beside it (geoloc/data/tile_context.py; at most 0.5), and the query's view is matched over it: a camera near the
    # edge keeps imagery under the part of its view that leaves the tile; 0: the tile alone
    margin: float = 0.0

    def __post_init__(self):
        if self.stage not in STAGES:
            raise ValueError(f"refiner.stage must be one of {STAGES}, got {self.stage!r}")
        if not 0.0 <= self.orientation_noise_deg <= 180.0:
            raise ValueError(f"refiner.orientation_noise_deg must lie in [0, 180], got {self.orientation_noise_deg}")
        if self.weight <= 0 or self.size < 0 or self.size % 2:
            raise ValueError(f"refiner.weight must be > 0 and refiner.size an even number >= 0 (0: "
                             f"dataset.aerial_size); got weight={self.weight}, size={self.size}")
        if not (np.isfinite(self.query_extent_m) and self.query_extent_m >= 0):
            raise ValueError(f"refiner.query_extent_m must be a number of metres >= 0 (0: no scale input), got "
                             f"{self.query_extent_m}")
        if not (np.isfinite(self.edge_weight) and self.edge_weight > 0):
            raise ValueError(f"refiner.edge_weight must be a weight > 0 (1: every truth alike), got {self.edge_weight}")
        if not 0.0 <= self.margin <= 0.5:
            raise ValueError(f"refiner.margin must be a share of the tile's side in [0, 0.5] (0: the tile alone; the "
                             f"tiles beside it reach half a tile beyond each edge), got {self.margin}")
        if not 0.0 <= self.peak_smoothing <= 0.5:
            raise ValueError(f"refiner.peak_smoothing must be a share of the tile's side in [0, 0.5] (0: the raw "
                             f"peak), got {self.peak_smoothing}")

    def loss(self, nll: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
        """The refiner's loss: the (B,) negative log-likelihoods of the truths at (B, 2) tile fractions, averaged
        with edge_weight on the truths near the tile's edge."""
        if self.edge_weight == 1.0:
            return nll.mean()
        weight = torch.where(near_edge(truth), self.edge_weight, 1.0).to(nll.dtype)
        return (weight * nll).sum() / weight.sum()

    def side(self, aerial_size: int) -> int:
        return self.size or aerial_size

    def query_scale(self, extent_m) -> torch.Tensor | None:
        """(B,) how many times larger each pair's query map is drawn for tiles of (B, 2) (height, width) metres,
        or None without the scale input (query_extent_m = 0)."""
        if not self.query_extent_m:
            return None
        width = torch.as_tensor(np.asarray(extent_m, np.float64), dtype=torch.float32).reshape(-1, 2)[:, 1]
        if not bool(torch.isfinite(width).all()):
            raise ValueError("refiner.query_extent_m needs each tile's ground extent; these tiles have no metres "
                             "per pixel (set refiner.query_extent_m=0, or give the dataset's scale)")
        return self.query_extent_m / width

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


def match(refiner, refine: RefineConfig, query_maps, reference_maps, candidates, extent_m=None):
    """refiner.match of B pairs, with the query's scale for tiles of extent_m ((B, 2) metres) where the refiner
    takes the ground scale as an input; a refiner that does not is called as before (a plug-in need not know it)."""
    scale = None if extent_m is None else refine.query_scale(extent_m)
    if scale is None:
        return refiner.match(query_maps, reference_maps, candidates)
    return refiner.match(query_maps, reference_maps, candidates, query_scale=scale.to(query_maps.device))


def matcher(refiner, query_map, candidates, scale=None):
    """match of one query map (1 x C x n x n) against tiles of one query scale (a factor, None without the scale
    input) that come in parts: a function of reference maps -> their Refinement, the query's side computed once
    where the refiner can (its `matcher`); a refiner without one is matched with the map expanded to each part."""
    if callable(getattr(refiner, "matcher", None)):
        return refiner.matcher(query_map, candidates, scale)

    def matched(reference_maps):
        b = len(reference_maps)
        scales = {} if scale is None else {"query_scale": torch.as_tensor(scale).reshape(1).expand(b)}
        return refiner.match(query_map.expand(b, *query_map.shape[1:]), reference_maps, candidates, **scales)
    return matched


# ---- metrics ------------------------------------------------------------------------------------------------
def fine_plan(split: RetrievalSplit | None, refine: RefineConfig) -> list:
    """The key sets refinement reports on `split`: metres where the tiles' scale is known (over the whole tile where
    the split gives semi-positives), the heading when it is unknown, end to end where the split has positions and
    is not one-to-one. split=None: every key set some split could give (what the config alone says)."""
    scaled = split is None or split.reference_metres_per_px is not None
    plan = [FINE_KEYS] if scaled else []
    if plan and (split is None or split.semi_positives is not None and split.query_semi_tile_px is not None):
        plan.append(WHOLE_TILE_KEYS)
    if refine.orientation_noise_deg > 0:
        plan.append(FINE_HEADING_KEYS)
    if scaled and (split is None or split.positions()[0] is not None and not split.one_to_one):
        plan.append(E2E_KEYS)
    return plan


@torch.no_grad()
def refined(refiner, refine: RefineConfig, query_maps: torch.Tensor, reference_maps: torch.Tensor, queries,
            tiles, candidates: torch.Tensor, split: RetrievalSplit | None = None,
            chunk: int = 64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The pairs (query_maps[queries[p]], reference_maps[tiles[p]]) matched: ((P, 2) tile fractions, (P,) headings,
    and where `split` gives the tiles' extent the (P,) probability mass within RADIUS_M of each position, the
    refiner's own score that a calibrator maps to P(error <= RADIUS_M); else None). The extent also gives the
    query's scale where the refiner takes it (RefineConfig.query_scale)."""
    queries, tiles = torch.as_tensor(np.asarray(queries)), torch.as_tensor(np.asarray(tiles))
    extents = None if split is None or split.reference_extent_m is None else split.reference_extent_m[tiles.numpy()]
    positions, headings, masses = [], [], []
    for start in range(0, len(tiles), chunk):
        part = slice(start, start + chunk)
        extent = None if extents is None else extents[part]
        out = match(refiner, refine, query_maps[queries[part]], reference_maps[tiles[part]], candidates, extent)
        metres = (None if extent is None else
                  torch.as_tensor(np.asarray(extent, np.float64), dtype=torch.float32).to(query_maps.device))
        position, mass = read_answer(out, refine, RADIUS_M, metres)
        positions.append(position.float().cpu())
        headings.append(out.heading().float().cpu())
        if mass is not None:
            masses.append(mass.float().cpu())
    return torch.cat(positions), torch.cat(headings), torch.cat(masses) if masses else None


def read_answer(out, refine: RefineConfig, radius_m: float, extent_m: torch.Tensor | None):
    """(B x 2 tile fractions, (B,) the mass within radius_m of them, or None without extent_m) of a refiner's answer
    `out`, read with refine.peak_smoothing where it is set (the blurred answer reused for the mass, not blurred
    twice); without the key exactly as before, so a plug-in's answer object that predates it is read as it was."""
    if not refine.peak_smoothing:
        return out.position(), None if extent_m is None else out.mass_within(radius_m, extent_m)
    position = out.position(refine.peak_smoothing)
    mass = None if extent_m is None else out.mass_within(radius_m, extent_m, refine.peak_smoothing, at=position)
    return position, mass


def fine_metrics(refiner, split: RetrievalSplit, refine: RefineConfig, candidates: torch.Tensor,
                 query_maps: torch.Tensor, reference_maps: torch.Tensor, true_heading: torch.Tensor,
                 top1: Callable[[], np.ndarray] | None = None, answers: TileAnswers | None = None) -> dict[str, float]:
    """fine_plan(split)'s metrics: each query refined in its positive tile (the fine-grained protocol), in every
    tile that holds it (the whole tile), and in its top-1 retrieved tile (end to end: the tile centre's position
    plus the refined offset, against the query's). The one report of a refiner, in validation, evaluate.py and the
    gallery path. top1(): (Q,) each query's top-1 retrieved tile (the scorer's top_k, or a saved gallery's search),
    asked only where the plan reports end to end; answers: the whole-tile answers (whole_tile_answers) where the
    caller has them already."""
    out: dict = {}
    plan = fine_plan(split, refine)
    rows = np.arange(split.num_queries)
    position, heading, _ = refined(refiner, refine, query_maps, reference_maps, rows, split.positives, candidates,
                                   split)
    if FINE_KEYS in plan:
        shown = shown_queries(split)
        errors = pair_errors_m(position.numpy(), split, rows, split.positives)[shown]
        out.update(fine_summary(errors), **labels_of(split))
    if WHOLE_TILE_KEYS in plan:
        if answers is None:
            answers = whole_tile_answers(refiner, refine, split, candidates, query_maps, reference_maps)
        out.update(whole_tile_summary(answers.error_m, answers.truth))
    if FINE_HEADING_KEYS in plan:
        out.update(heading_summary(circular_error_deg(heading.numpy(), true_heading.cpu().numpy())))
    if E2E_KEYS in plan:
        tiles = np.asarray(top1(), np.int64)
        e2e_position, _, _ = refined(refiner, refine, query_maps, reference_maps, rows, tiles, candidates, split)
        out.update(e2e_summary(e2e_errors_m(e2e_position.numpy(), tiles, split)))
    return out


def refiner_metrics(task, split: RetrievalSplit | None, maps: dict, top1: Callable[[], np.ndarray] | None = None,
                    answers: TileAnswers | None = None) -> dict[str, float]:
    """fine_metrics of `task`'s refiner from encode.described's entries of `split`'s queries and tiles
    ("refine_query", "refine_reference", "refine_heading"; top1 by default the exact ranking of its "query" and
    "reference" descriptors), as validation and the gallery path report it; {} without a refiner or a split."""
    if task.refiner is None or split is None:
        return {}
    top1 = top1 or (lambda: top_k(maps["query"], maps["reference"], 1)[1][:, 0].cpu().numpy())
    return fine_metrics(task.refiner, split, task.refine, task.refine_candidates(), maps["refine_query"],
                        maps["refine_reference"], maps["refine_heading"], top1, answers)


def labels_of(split: RetrievalSplit) -> dict[str, str]:
    """{METRE_LABELS: the label set the split's truth positions come from}, reported beside every fine metre."""
    return {METRE_LABELS: split.tile_labels or "unknown"}


class TileAnswers(NamedTuple):
    """The refiner's answers for P query-tile pairs."""

    mass: np.ndarray  # (P,) the probability mass within RADIUS_M of the answer: the refiner's own score
    error_m: np.ndarray  # (P,) metres from the truth
    truth: np.ndarray  # (P, 2) the truth's tile fraction
    positive: np.ndarray  # (P,) bool: the pair's tile is the query's positive


def whole_tile_answers(refiner, refine: RefineConfig, split: RetrievalSplit, candidates: torch.Tensor,
                       query_maps: torch.Tensor, reference_maps: torch.Tensor, queries=None) -> TileAnswers:
    """Each of `queries` (default: every query a tile shows, `shown_queries`) refined in every tile that holds it
    (tile_pairs). What the "within_5m" confidence is fitted on and scored against (geoloc/gallery/confidence.py), and the
    whole-tile metres."""
    if split.reference_metres_per_px is None:
        raise ValueError(f"{split.name}: its tiles have no metres per pixel, so a metre error has no meaning")
    rows, tiles = tile_pairs(split, True, np.flatnonzero(shown_queries(split)) if queries is None else queries)
    position, _, mass = refined(refiner, refine, query_maps, reference_maps, rows, tiles, candidates, split)
    truth = np.stack([truth_fraction(split, int(q), int(t)) for q, t in zip(rows, tiles)])
    return TileAnswers(mass.double().numpy(), fraction_error_m(position.numpy(), truth, split, tiles), truth,
                       tiles == split.positives[rows])


def pair_errors_m(position: np.ndarray, split: RetrievalSplit, queries, tiles) -> np.ndarray:
    """(P,) metres between the (P, 2) refined tile fractions of queries[p] in tiles[p] and their truths."""
    truth = np.stack([truth_fraction(split, int(q), int(t)) for q, t in zip(queries, tiles)])
    return fraction_error_m(position, truth, split, tiles)


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
