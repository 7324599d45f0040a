"""One query's localisation: the retrieved tiles, where the query is and which way it looks, and how sure.

localize.py prints `to_json()` as one JSON line, `geoloc serve` answers with it; code that localizes queries in
bulk (evaluation) builds the same object. Retrieval fills the tiles, the top-1 tile's position and the heading; the
fields of metric localisation inside the tile (a refined position, a probability map over the tile, a confidence)
stay None until a method fills them, and to_json() leaves out what is None, so an answer is exactly what retrieval
alone gives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# to_json()'s keys in order, the optional ones included where set
JSON_KEYS = ("image", "fov_deg", "heading_deg", "heading_source", "position", "topk", "positions", "truth",
             "refined_position", "confidence", "calibrated", "abstained", "picture")
OPTIONAL = ("truth", "refined_position", "confidence", "calibrated", "abstained", "picture")


@dataclass
class LocalizationResult:
    """image: the query's name (file name or path) or None; fov_deg: its horizontal field of view;
    heading_deg: its bearing in degrees clockwise from north (the top-1 tile's best candidate heading, or the one
    given), heading_source "search" | "given" | "prior" (searched within ± heading_prior of the given heading);
    topk: the retrieved tiles, best first: {"rank", "row" (gallery row), "path", the tile's position keys
    ("lat", "lon" or "x_m", "y_m") where the gallery has positions, "score", "heading_deg"};
    position: the top-1 tile's position keys, or None; positions: their kind, "latlon" | "xy" | None;
    truth: for a query of the gallery's split, its true row, reference, rank among the top-k, position and the
    top-1's metre error;
    refined_position: the position inside the top-1 tile a metric-localisation method finds (position keys);
    probability_map: H×W float, that method's probability of each tile pixel (not in the JSON: too large);
    confidence: the probability the answer is right, in [0, 1] (retrieval: that the top-1 tile is the query's
    positive; docs/confidence.md), None where the gallery holds no calibration for this query's condition;
    calibrated: whether confidence is given (False: the gallery is uncalibrated, or the query's condition is not
    the one it was calibrated for); abstained: with an abstain threshold, whether the confidence is below it;
    picture: the file of the answer's picture, once drawn."""

    image: str | None
    fov_deg: float
    heading_deg: float
    heading_source: str
    topk: list[dict]
    position: dict | None = None
    positions: str | None = None
    truth: dict | None = None
    refined_position: dict | None = None
    probability_map: np.ndarray | None = None
    confidence: float | None = None
    calibrated: bool | None = None
    abstained: bool | None = None
    picture: str | None = None

    def __post_init__(self):
        if self.heading_source not in ("search", "given", "prior"):
            raise ValueError(f"heading_source must be 'search', 'given' or 'prior', got {self.heading_source!r}")
        if self.confidence is not None and not 0.0 <= self.confidence <= 1.0:
            raise ValueError(f"confidence must be a probability in [0, 1], got {self.confidence}")

    @property
    def rows(self) -> list[int]:
        """The retrieved gallery rows, best first."""
        return [hit["row"] for hit in self.topk]

    @property
    def scores(self) -> list[float]:
        return [hit["score"] for hit in self.topk]

    def to_json(self) -> dict:
        """The answer as localize.py and the service write it: plain JSON types, the optional keys only where set."""
        return {key: getattr(self, key) for key in JSON_KEYS
                if key not in OPTIONAL or getattr(self, key) is not None}
