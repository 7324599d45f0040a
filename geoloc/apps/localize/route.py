"""A route of street frames in, a track out: each frame answered against the saved gallery by the Localizer, the
answers fused with the route's odometry by the sequence filter (geoloc/sequence/particle_filter.py).

The filter works in metres on one plane. A gallery's tile positions are (lat, lon) degrees or (x, y) metres of one
projected frame. Metres of one frame are the plane as they are. Degrees may span places far apart (synthetic VIGOR's
four cities, or a gallery of several states): the tiles are grouped into regions (single linkage: a tile within
REGION_LINK_TILES tile widths of a region's tile joins it), each region is drawn on its own tangent plane about
its centre (geoloc/data/geo.py), and the regions are laid side by side along the plane's east axis, REGION_GAP_M
apart, so that no route's odometry carries a hypothesis from one region into another. The filter's uniform prior
covers the regions' boxes, not the gaps between them (RegionsExtent).

Each frame's answer (LocalizationResult) becomes a FrameAnswer: its top-k tiles' centres and retrieval scores, and
where the refiner ran, each tile's refined position with the refiner's calibrated confidence that it is within 5 m
(`confidence_within_5m`), or, in a gallery without that calibration, its own mass within 5 m (`mass_5m`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from geoloc.data.geo import centre_latlon, latlon_to_offset, offset_to_latlon
from geoloc.gallery import POSITION_KEYS
from geoloc.sequence.estimate import FrameEstimate
from geoloc.sequence.extent import GalleryExtent, RegionsExtent
from geoloc.sequence.measurement import FrameAnswer
from geoloc.sequence.odometry import Odometry
from geoloc.sequence.particle_filter import FilterConfig, localize_route

REGION_LINK_TILES = 10.0  # tiles further apart than this many tile widths (and no chain between) are two regions
REGION_GAP_M = 100_000.0  # the regions' spacing on the filter's plane: further than any route drives


@dataclass
class RoutePlane:
    """The filter's plane for one gallery: region r's tiles at east offset `shift[r]`; kind "latlon" or "xy"."""

    kind: str
    origins: np.ndarray  # (R, 2) each region's tangent-plane origin (lat, lon), or zeros for "xy"
    shift: np.ndarray  # (R,) each region's east offset on the plane, metres
    region_of_tile: np.ndarray  # (N,) the region of each gallery row
    tiles: np.ndarray  # (N, 2) each tile centre on the plane, metres
    extent: RegionsExtent

    @classmethod
    def of(cls, kind: str, positions, tile_width_m: float) -> RoutePlane:
        """The plane of N tile positions of `kind` (the gallery's places.kind and reference_positions)."""
        positions = np.asarray(positions, np.float64)
        if kind == "xy":
            zero = np.zeros(1)
            extent = RegionsExtent([GalleryExtent.from_centres(positions, tile_width_m)])
            return cls(kind, np.zeros((1, 2)), zero, np.zeros(len(positions), np.int64), positions, extent)
        if kind != "latlon":
            raise ValueError(f"a route needs a gallery with tile positions ('latlon' or 'xy'), got {kind!r}")
        region = regions_of(positions, REGION_LINK_TILES * tile_width_m)
        origins = np.stack([centre_latlon(positions[region == r]) for r in range(region.max() + 1)])
        local = np.stack([latlon_to_offset(origins[r], p) for r, p in zip(region, positions)])
        boxes, shift, start = [], [], 0.0
        for r in range(len(origins)):  # side by side along east, REGION_GAP_M apart
            mine = local[region == r]
            shift.append(start - mine[:, 0].min())
            boxes.append(GalleryExtent.from_centres(mine + [shift[-1], 0.0], tile_width_m))
            start = boxes[-1].east_max + REGION_GAP_M
        shift = np.array(shift)
        return cls(kind, origins, shift, region, local + np.column_stack([shift[region], np.zeros(len(region))]),
                   RegionsExtent(boxes))

    def to_plane(self, position, row: int | None = None) -> np.ndarray:
        """(2,) a position of the gallery's kind on the plane, in the region of gallery row `row`'s tile (None: the
        region whose centre is nearest)."""
        if self.kind == "xy":
            return np.asarray(position, np.float64)
        if row is None:
            r = int(np.argmin(np.linalg.norm(latlon_to_offset(np.asarray(position, np.float64), self.origins), axis=1)))
        else:
            r = self.region_of_tile[row]
        return latlon_to_offset(self.origins[r], position) + [self.shift[r], 0.0]

    def from_plane(self, point) -> np.ndarray:
        """(2,) a point of the plane as a position of the gallery's kind (the nearest region's frame)."""
        point = np.asarray(point, np.float64)
        if self.kind == "xy":
            return point
        r = int(np.argmin(np.abs(self.extent.centres()[:, 0] - point[0])))
        return offset_to_latlon(self.origins[r], point[0] - self.shift[r], point[1])

    def answer(self, result) -> FrameAnswer:
        """A LocalizationResult's top-k as the filter's FrameAnswer."""
        rows = [hit["row"] for hit in result.topk]
        keys = POSITION_KEYS[self.kind]
        refined = [hit.get("refined_position") for hit in result.topk]
        if all(r is not None for r in refined):
            points = np.stack([self.to_plane([r[k] for k in keys], row) for r, row in zip(refined, rows)])
            confidence = np.array([r.get("confidence_within_5m", r["mass_5m"]) for r in refined])
        else:
            points = confidence = None
        return FrameAnswer(self.tiles[rows], np.array([hit["score"] for hit in result.topk]), points, confidence)

    def estimate_json(self, estimate: FrameEstimate, level: float = 0.95) -> dict:
        """One frame's estimate as the output writes it: the position (the gallery's keys), the heading, the
        covariance in east/north metres squared, the share of the posterior the track holds and the `level`
        region's area."""
        where = self.from_plane(estimate.position)
        return {"position": dict(zip(POSITION_KEYS[self.kind], map(float, where))),
                "heading_deg": float(estimate.heading_deg),
                "covariance_m2": np.asarray(estimate.covariance, float).round(3).tolist(),
                "tracked_mass": float(estimate.tracked_mass),
                f"region_{round(level * 100)}_area_m2": float(estimate.region_area_m2(level)),
                f"region_{round(level * 100)}_whole_gallery": bool(estimate.whole_gallery(level))}


def regions_of(latlon: np.ndarray, link_m: float) -> np.ndarray:
    """(N,) region labels 0.. of (N, 2) (lat, lon) positions: single-linkage clusters at link_m metres, numbered
    by their first position."""
    from scipy.cluster.hierarchy import fcluster, linkage

    if len(latlon) == 1:
        return np.zeros(1, np.int64)
    # a tangent plane about the centre is good enough to tell near from far; metres within a region come from
    # each region's own plane
    local = latlon_to_offset(centre_latlon(latlon), latlon)
    labels = fcluster(linkage(local, "single"), t=link_m, criterion="distance")
    _, first = np.unique(labels, return_index=True)
    order = {labels[i]: k for k, i in enumerate(sorted(first))}
    return np.array([order[label] for label in labels], np.int64)


def route_plane(places, config: FilterConfig) -> RoutePlane:
    """The filter's plane of a saved gallery's places (ValueError when its tiles have no positions). The tiles' width
    is their median ground extent, or, in a gallery without one (CVUSA's, CVACT's), twice tile_sigma_m."""
    if places.kind is None:
        raise ValueError("a route needs a gallery whose tiles have positions (lat/lon or x/y): this one has none; "
                         "save a gallery of a split with positions (docs/sequence.md)")
    width = (2 * config.tile_sigma_m if places.reference_extent_m is None
             else float(np.median(places.reference_extent_m[:, 1])))
    return RoutePlane.of(places.kind, places.reference_positions, width)


class RouteTrack(NamedTuple):
    """A route fused: one line per frame (its name, the filtered estimate, the frame's own answer), and the frames'
    FrameAnswers and FrameEstimates they come from."""

    lines: list[dict]
    answers: list[FrameAnswer]
    estimates: list[FrameEstimate]


def track(plane: RoutePlane, frames: list[Path], results: list, odometry: Odometry, config: FilterConfig,
          out: Path, picture: bool = True, seed: int = 0) -> list[dict]:
    """The route's track (fused) written to out/route.jsonl, one line per frame, and drawn in out/route.png;
    returns the lines."""
    route = fused(plane, [frame.name for frame in frames], results, odometry, config, seed)
    with open(out / "route.jsonl", "w") as file:
        file.writelines(json.dumps(line) + "\n" for line in route.lines)
    print(json.dumps({"route": str(out / "route.jsonl"), "frames": len(route.lines), "last": route.lines[-1]}))
    if picture:
        from geoloc.apps.localize.route_figure import route_figure

        route_figure(plane, route.estimates, route.answers, truth_of(frames[0].parent, plane), out / "route.png")
    return route.lines


def fused(plane: RoutePlane, names: list[str], results: list, odometry: Odometry, config: FilterConfig,
          seed: int = 0) -> RouteTrack:
    """Each frame's answer (`results`, the localizer's, in frame order) fused with `odometry`."""
    answers = [plane.answer(r) for r in results]
    estimates = localize_route(answers, odometry, plane.extent, config, seed)
    lines = []
    for name, result, estimate in zip(names, results, estimates):
        single = result.refined_position or result.position
        lines.append({"frame": name, **plane.estimate_json(estimate),
                      "frame_answer": {k: single[k] for k in POSITION_KEYS[plane.kind]}})
    return RouteTrack(lines, answers, estimates)


def truth_of(folder: Path, plane: RoutePlane) -> np.ndarray | None:
    """(F, 2) the frames' true positions on the plane from folder/truth.csv (what the synthetic routes write: lat,
    lon, or x_m, y_m columns), or None without one."""
    path = folder / "truth.csv"
    if not path.is_file():
        return None
    table = np.genfromtxt(path, delimiter=",", names=True)
    keys = POSITION_KEYS[plane.kind]
    if not all(k in (table.dtype.names or ()) for k in keys):
        return None
    return np.stack([plane.to_plane(p) for p in np.column_stack([np.atleast_1d(table[k]) for k in keys])])
