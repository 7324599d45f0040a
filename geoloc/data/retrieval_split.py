"""One split of a retrieval dataset where a query may match any reference, not just reference i.

The one-to-one datasets (CVUSA, CVACT) are the special case positives = arange(Q). VIGOR adds semi-positives
(references that contain the query's location off centre) and GPS; University-1652 adds labels (every image of
the query's building is relevant). Which references are relevant to a query is said here once, by
`RetrievalSplit.relevance` (geoloc/data/relevance.py), and every metric path ranks by it (docs/conventions.md
"Relevance").
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from geoloc.data.relevance import Relevance

QUERY_VIEWS = ("panorama", "sphere", "image", "aerial")
# the fields that hold one row per query / per reference (what cutting a split to fewer rows cuts)
PER_QUERY = ("queries", "positives", "semi_positives", "query_latlon", "query_xy", "query_labels", "query_tile_px",
             "query_semi_tile_px")
# the label sets query_tile_px comes from (RetrievalSplit.tile_labels), each metre figure measured against it names
TILE_LABELS = {
    "vigor_corrected": "SliceMatch's corrected VIGOR labels, at each city's metres per pixel",
    "vigor_original": "VIGOR's original labels, converted from the 0.114 m a pixel they were made at",
    "synthetic": "the synthetic renderer's exact positions",
    "tile_centre": "the camera at the tile centre",
    "positions": "the query and tile positions given with the images",
}
PER_REFERENCE = ("references", "reference_latlon", "reference_xy", "reference_labels", "reference_size_px",
                 "reference_metres_per_px")


@dataclass(frozen=True)
class RetrievalSplit:
    """name: e.g. "vigor/same_area/test"; root: the dataset folder the paths were read from.

    queries (Q paths), references (N paths);
    positives (Q,) int: each query's positive reference index;
    semi_positives (Q, S) int or None: further references that hold the query's place, -1 for none;
    query_latlon (Q, 2), reference_latlon (N, 2) float degrees or None (VIGOR: from the file names);
    query_xy (Q, 2), reference_xy (N, 2) float metres (easting, northing) in one projected frame, or None: CVACT's
    UTM (`utm` in ACT_data.mat), the synthetic layouts' `positions.csv` (docs/datasets.md);
    query_labels (Q,), reference_labels (N,) int or None: place / building ids, given together; a reference is
    relevant to a query when their labels are equal (University-1652's AP counts all of them);
    query_view: what a query image is, so the data module knows how to align it: "panorama" (CVUSA's horizon band),
    "sphere" (a full-sphere equirectangular panorama, cropped to its horizon band: CVACT, VIGOR) or "image" (a
    perspective photo, e.g. a University-1652 drone view, which no polar transform applies to) or "aerial" (the
    query is the aerial image and the references are photos: University-1652's satellite -> drone; each image is
    still encoded by its own view's branch).
    relevance_radius_m: None, or the VPR convention: a query's positive and every reference within this many
    metres of it are relevant (needs positions; `relevance`);
    radius_alone: with relevance_radius_m, the radius alone decides, as gmberton's VPR-methods-evaluation does: the
    positive is relevant only within it, and a query with no reference that near has nothing relevant.

    Tile geometry and where each query lies in its tiles (the seams of metric localisation; docs/datasets.md):
    reference_size_px (N, 2) int (height, width) or None: the pixel frame of each tile as released (VIGOR 640 x 640);
    reference_metres_per_px (N,) float > 0 or None: ground metres per tile pixel (VIGOR's per-city scale, the
    synthetic renderer's); needs reference_size_px. The tile's extent is reference_extent_m;
    query_tile_px (Q, 2) float (row, col) or None: the query's position in its positive tile, in continuous pixel
    coordinates of that frame ((0, 0) the top-left corner, (H/2, W/2) the tile centre, rows south, columns east);
    (NaN, NaN) where it is unknown: a test query that no tile shows (own data under the radius rule keeps it);
    query_semi_tile_px (Q, S, 2) float or None: the same in each semi-positive, NaN where semi_positives is -1; a
    position may lie outside its tile (SliceMatch's corrected VIGOR labels: at the true scale some panoramas are not
    in a "semi-positive" tile), and only positions inside a tile are used (semi_inside);
    tile_labels: the label set query_tile_px comes from (a key of TILE_LABELS), which every metre figure measured
    against it names; None where the split has no positions in its tiles.
    """

    name: str
    root: Path
    queries: list
    references: list
    positives: np.ndarray
    semi_positives: np.ndarray | None = None
    query_latlon: np.ndarray | None = None
    reference_latlon: np.ndarray | None = None
    query_xy: np.ndarray | None = None
    reference_xy: np.ndarray | None = None
    query_labels: np.ndarray | None = None
    reference_labels: np.ndarray | None = None
    query_view: str = "panorama"  # panorama | sphere | image | aerial: see above
    relevance_radius_m: float | None = None  # VPR: every reference within this radius is relevant too
    radius_alone: bool = False  # with relevance_radius_m: the positive is not relevant beyond it
    reference_size_px: np.ndarray | None = None
    reference_metres_per_px: np.ndarray | None = None
    query_tile_px: np.ndarray | None = None
    query_semi_tile_px: np.ndarray | None = None
    tile_labels: str | None = None

    def __post_init__(self):
        put = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731  (frozen: set once, here)
        put("root", Path(self.root))
        if self.query_view not in QUERY_VIEWS:
            raise ValueError(f"{self._where()}: query_view must be one of {QUERY_VIEWS}, got {self.query_view!r}")
        put("queries", [Path(p) for p in self.queries])
        put("references", [Path(p) for p in self.references])
        q, n = len(self.queries), len(self.references)
        if q == 0 or n == 0:
            raise ValueError(f"{self._where()} has {q} queries and {n} references; both must be at least 1")
        put("positives", self._ints("positives", self.positives, (q,), 0, n))
        if self.semi_positives is not None:
            semi = np.asarray(self.semi_positives)
            shape = (q, semi.shape[1] if semi.ndim == 2 else 0)
            put("semi_positives", self._ints("semi_positives", semi, shape, -1, n))
        for key, rows in (("query_latlon", q), ("reference_latlon", n)):
            if getattr(self, key) is not None:
                put(key, self._latlon(key, getattr(self, key), rows))
        for key, rows in (("query_xy", q), ("reference_xy", n)):
            if getattr(self, key) is not None:
                put(key, self._xy(key, getattr(self, key), rows))
        if self.relevance_radius_m is not None:
            radius = float(self.relevance_radius_m)
            if not np.isfinite(radius) or radius < 0 or self.positions()[0] is None:
                raise ValueError(f"{self._where()}: relevance_radius_m={self.relevance_radius_m} needs query and "
                                 "reference positions and a finite radius >= 0 (metres)")
            if self.query_labels is not None:
                raise ValueError(f"{self._where()}: give labels or relevance_radius_m, not both: each defines "
                                 "which references are relevant")
        elif self.radius_alone:
            raise ValueError(f"{self._where()}: radius_alone needs relevance_radius_m, the radius that decides")
        if (self.query_labels is None) != (self.reference_labels is None):
            raise ValueError(f"{self._where()}: give query_labels and reference_labels together, or neither")
        if self.query_labels is not None:
            put("query_labels", self._ints("query_labels", self.query_labels, (q,), None, None))
            put("reference_labels", self._ints("reference_labels", self.reference_labels, (n,), None, None))
            wrong = np.flatnonzero(self.reference_labels[self.positives] != self.query_labels)
            if len(wrong):
                i = int(wrong[0])
                raise ValueError(f"{self._where()}: query {i} ({self.queries[i]}) has label {self.query_labels[i]} "
                                 f"but its positive reference {self.positives[i]} has label "
                                 f"{self.reference_labels[self.positives[i]]} ({len(wrong)} such queries)")
        self._check_tiles(put)
        if self.tile_labels is not None and self.tile_labels not in TILE_LABELS:
            raise ValueError(f"{self._where()}: tile_labels must be one of {sorted(TILE_LABELS)}, got "
                             f"{self.tile_labels!r}")

    @cached_property
    def relevance(self) -> Relevance:
        """Which references are relevant to each query, the one definition every metric ranks by: with labels,
        every reference of the query's label (University-1652); with ``relevance_radius_m``, every reference
        within that radius and, unless ``radius_alone``, the positive (VPR); otherwise the positive (the
        one-to-one data, VIGOR), the semi-positives set aside by VIGOR's hit rate only."""
        if self.query_labels is not None:
            return Relevance.from_labels(self.query_labels, self.reference_labels)
        if self.relevance_radius_m is not None:
            kind, query_positions, reference_positions = self.positions()
            return Relevance.within_radius(None if self.radius_alone else self.positives, query_positions,
                                           reference_positions, kind, self.relevance_radius_m)
        if self.one_to_one:
            return Relevance.one_to_one(self.num_queries, self.num_references)
        return Relevance.from_positives(self.positives, self.num_references, self.semi_positives)

    def positions(self) -> tuple[str | None, np.ndarray | None, np.ndarray | None]:
        """(kind, query positions, reference positions): "latlon" (degrees: VIGOR's file names, a positions.csv
        in degrees), "xy" (metres, e.g. CVACT's UTM), or (None, None, None) when the dataset has none."""
        if self.reference_latlon is not None and self.query_latlon is not None:
            return "latlon", self.query_latlon, self.reference_latlon
        if self.reference_xy is not None and self.query_xy is not None:
            return "xy", self.query_xy, self.reference_xy
        return None, None, None

    @property
    def one_to_one(self) -> bool:
        """Query i matches reference i and nothing else: CVUSA / CVACT."""
        return (self.num_queries == self.num_references and self.semi_positives is None
                and self.query_labels is None and self.relevance_radius_m is None
                and bool((self.positives == np.arange(self.num_queries)).all()))

    def labels(self) -> np.ndarray:
        """(Q,) the place label of each query: its positive reference (queries of one place share it)."""
        return self.positives

    @property
    def aerial_queries(self) -> bool:
        return self.query_view == "aerial"

    @property
    def num_queries(self) -> int:
        return len(self.queries)

    @property
    def num_references(self) -> int:
        return len(self.references)

    def _where(self) -> str:
        return f"RetrievalSplit {self.name!r} (root {self.root})"

    def _ints(self, key: str, value, shape: tuple, low: int | None, high: int | None) -> np.ndarray:
        """An int64 array of the given shape with values in [low, high); a clear error otherwise."""
        a = np.asarray(value)
        if a.shape != shape:
            raise ValueError(f"{self._where()}: {key} has shape {a.shape}, expected {shape}")
        if a.size and not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"{self._where()}: {key} must hold integers, got dtype {a.dtype}")
        a = a.astype(np.int64)
        if a.size and low is not None and (a.min() < low or a.max() >= high):
            bad = int(np.flatnonzero((a < low) | (a >= high))[0]) // max(1, int(np.prod(shape[1:])))
            raise ValueError(f"{self._where()}: {key} must lie in [{low}, {high}) (the reference indices"
                             f"{', -1 for none' if low == -1 else ''}); query {bad} has {a[bad].tolist()}")
        return a

    def _xy(self, key: str, value, rows: int) -> np.ndarray:
        a = np.asarray(value, np.float64)
        if a.shape != (rows, 2):
            raise ValueError(f"{self._where()}: {key} has shape {a.shape}, expected ({rows}, 2) of (x, y) metres")
        if not np.isfinite(a).all():
            i = int(np.flatnonzero(~np.isfinite(a).all(1))[0])
            raise ValueError(f"{self._where()}: {key} row {i} = {a[i].tolist()} is not a finite (x, y) in metres")
        return a

    def _latlon(self, key: str, value, rows: int) -> np.ndarray:
        a = np.asarray(value, np.float64)
        if a.shape != (rows, 2):
            raise ValueError(f"{self._where()}: {key} has shape {a.shape}, expected ({rows}, 2) of (lat, lon)")
        ok = np.isfinite(a).all(1) & (np.abs(a[:, 0]) <= 90) & (np.abs(a[:, 1]) <= 180)
        if not ok.all():
            i = int(np.flatnonzero(~ok)[0])
            raise ValueError(f"{self._where()}: {key} row {i} = {a[i].tolist()} is not a (lat, lon) in degrees")
        return a

    @property
    def reference_extent_m(self) -> np.ndarray | None:
        """(N, 2) ground metres (height, width) each tile covers, or None where the scale is unknown."""
        if self.reference_metres_per_px is None:
            return None
        return self.reference_size_px * self.reference_metres_per_px[:, None]

    def query_tile_offset_m(self) -> np.ndarray | None:
        """(Q, 2) (east, north) metres of each query from its positive tile's centre (NaN where query_tile_px is), or
        None where the split lacks the query positions or the tiles' scale."""
        if self.query_tile_px is None or self.reference_metres_per_px is None:
            return None
        size = self.reference_size_px[self.positives]
        scale = self.reference_metres_per_px[self.positives]
        row, col = self.query_tile_px[:, 0], self.query_tile_px[:, 1]
        return np.column_stack([(col - size[:, 1] / 2) * scale, (size[:, 0] / 2 - row) * scale])

    def _check_tiles(self, put) -> None:
        """The tile geometry and the query positions in the tiles (class docstring), checked and normalised."""
        q, n = self.num_queries, self.num_references
        needs_size = [k for k in ("reference_metres_per_px", "query_tile_px", "query_semi_tile_px")
                      if getattr(self, k) is not None]
        if self.reference_size_px is None:
            if needs_size:
                raise ValueError(f"{self._where()}: {needs_size[0]} needs reference_size_px, the pixel frame of "
                                 "the tiles it refers to")
            return
        size = self._ints("reference_size_px", self.reference_size_px, (n, 2), None, None)
        if size.size and size.min() < 1:
            i = int(np.flatnonzero((size < 1).any(1))[0])
            raise ValueError(f"{self._where()}: reference_size_px row {i} = {size[i].tolist()} is not a "
                             "(height, width) of at least 1 pixel")
        put("reference_size_px", size)
        if self.reference_metres_per_px is not None:
            scale = np.asarray(self.reference_metres_per_px, np.float64)
            if scale.shape != (n,):
                raise ValueError(f"{self._where()}: reference_metres_per_px has shape {scale.shape}, expected "
                                 f"({n},), one scale per reference")
            bad = ~(np.isfinite(scale) & (scale > 0))
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise ValueError(f"{self._where()}: reference_metres_per_px[{i}] = {scale[i]} ({self.references[i]}) "
                                 "is not a positive number of metres per pixel")
            put("reference_metres_per_px", scale)
        if self.query_tile_px is not None:
            put("query_tile_px", self._tile_px("query_tile_px", self.query_tile_px, (q, 2),
                                               self.positives[:, None], inside=True))
        if self.query_semi_tile_px is not None:
            if self.semi_positives is None:
                raise ValueError(f"{self._where()}: query_semi_tile_px needs semi_positives, the tiles it refers to")
            s = self.semi_positives.shape[1]
            put("query_semi_tile_px", self._tile_px("query_semi_tile_px", self.query_semi_tile_px, (q, s, 2),
                                                    self.semi_positives, inside=False))

    def semi_inside(self) -> np.ndarray | None:
        """(Q, S) bool: the semi-positives whose position lies inside their tile (None without positions)."""
        if self.query_semi_tile_px is None:
            return None
        frame = self.reference_size_px[np.maximum(self.semi_positives, 0)]
        pos = self.query_semi_tile_px
        return (self.semi_positives >= 0) & (pos >= 0).all(-1) & (pos <= frame).all(-1)

    def _tile_px(self, key: str, value, shape: tuple, tiles: np.ndarray, inside: bool) -> np.ndarray:
        """(row, col) positions in the given tiles ((Q, S) reference indices, -1 for none): finite (and with
        `inside`, inside each tile's pixel frame) where a tile is given, or (NaN, NaN) where the position is
        unknown; NaN where no tile is."""
        a = np.asarray(value, np.float64)
        if a.shape != shape:
            raise ValueError(f"{self._where()}: {key} has shape {a.shape}, expected {shape} of (row, col) pixels")
        a = a.reshape(shape[0], -1, 2).copy()
        given = tiles >= 0
        frame = self.reference_size_px[np.where(given, tiles, 0)]
        ok = np.isfinite(a).all(-1)
        if inside:
            ok &= (a >= 0).all(-1) & (a <= frame).all(-1)
        bad = given & ~ok & ~np.isnan(a).all(-1)
        if bad.any():
            i, j = (int(v) for v in np.argwhere(bad)[0])
            tile = int(tiles[i, j])
            where = (f"outside tile {tile} ({self.references[tile]}) of {frame[i, j].tolist()} pixels; a position is "
                     "(row, col) within (0, 0)..(height, width)") if inside else "not a finite (row, col)"
            raise ValueError(f"{self._where()}: {key} of query {i} ({self.queries[i]}) is {a[i, j].tolist()}, "
                             f"{where} ({bad.sum()} such)")
        a[~given] = np.nan
        return a.reshape(shape)
