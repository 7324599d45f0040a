"""One street image in, a position and a heading out: a checkpoint's query branch against a saved gallery.

The gallery is what `python evaluate.py ckpt=... gallery.save=DIR` writes (geoloc/tasks/crossview/gallery_build.py and
geoloc/gallery/places.py): the reference descriptors, where each reference is, and the split's queries. The heading is unknown in
general, so `heading=search` encodes the image at K candidate headings on the 360° canvas
(geoloc/tasks/crossview/views.py) and each reference keeps its best-scoring candidate: the score ranks the
references, the candidate is the heading estimate (a circular correlation through the query encoder, DSM-style).
`heading=` a number skips the search when it is known (north-aligned panoramas such as CVUSA's are heading 0);
`heading_prior=` with it searches only the candidates within ± that many degrees of it. A query that gives no
heading is answered as the checkpoint was trained (`default_heading`): searched when it was trained with an unknown
heading, else at north, since a model trained on north-aligned views loses most of its recall to a search
(docs/heading.md).

The confidence (docs/confidence.md) is the gallery's calibrated P(top-1 tile right), from the top-1 score and its
margin over the second; it is given where the query's condition is the one it was fitted in (the heading given,
exactly, at the fitted field of view), and `abstain=` marks answers below a threshold. A refined tile adds its own
`confidence_within_5m`: the gallery's calibrated P(the refined position is within 5 m | the tile holds the camera),
from the refiner's mass within 5 m; given where it was fitted for this checkpoint's refiner (its weights and test
condition) and where the refiner searches the heading itself (trained with an unknown heading) or the query's
heading is given exactly.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

from geoloc.apps.query import SEARCH, QueryError, QueryLimits, QuerySettings, check_headings, check_settings, check_size
from geoloc.config import ConfigError
from geoloc.data.geo import distance_m, offset_to_latlon
from geoloc.data.relevance import Relevance
from geoloc.eval.calibration import Calibrator, retrieval_features
from geoloc.eval.candidates import merge_headings, rank_candidates
from geoloc.eval.search_index import GalleryIndex
from geoloc.gallery import POSITION_KEYS, LocalizationResult, open_gallery
from geoloc.gallery.confidence import TOP1, WITHIN_5M, calibrators, refine_features, refiner_calibrator
from geoloc.tasks.crossview import CrossViewEncoder
from geoloc.tasks.crossview.views import headings_around

CANDIDATES_PER_PASS = 12  # candidate headings encoded per forward pass: bounds the activations of a heading search


class Localizer:
    """A cross-view checkpoint (its CrossViewEncoder) and a saved gallery, loaded once; `localize(image)` answers
    one image with a LocalizationResult.

    `localize` only reads the model and the index, so concurrent calls are safe; on a CPU they gain nothing from
    running at once (the service serialises them). `limits` bound what one image may cost (query.py)."""

    def __init__(self, encoder: CrossViewEncoder, index: GalleryIndex, places, info: dict,
                 heading_steps: int | None = None, limits: QueryLimits | None = None,
                 calibration: dict | None = None):
        self.encoder, self.index, self.places, self.meta = encoder, index, places, info
        self.calibration = calibration  # the gallery's calibration.json (None: saved without one)
        self.calibrator: Calibrator | None = calibrators(calibration).get(TOP1)
        # the refiner's, where it was fitted for this checkpoint's refiner, else why there is none
        self.within: Calibrator | str | None = (None if encoder.refiner is None else
                                                refiner_calibrator(calibration, encoder.refiner_condition))
        self.limits = limits.limits() if limits is not None else QueryLimits()
        # candidate headings of the search: as asked, else as the checkpoint's dataset config says
        self.device = encoder.device
        self.heading_steps = check_headings(heading_steps or encoder.data.heading_steps, self.limits)
        self.view = info.get("query_view", "panorama")
        self._tile_reader = None  # row -> the refiner's tile image (encoder.tile_reader), made at the first refine
        if self.view not in ("panorama", "sphere"):
            raise ConfigError(f"the gallery was built from {info.get('split')}, whose queries are {self.view} "
                              "images; localize takes street panoramas or limited-FoV street photos")

    @classmethod
    def load(cls, ckpt, gallery, device: str | None = None, heading_steps: int | None = None,
             limits: QueryLimits | None = None) -> "Localizer":
        """device: None or "auto" (the GPU when there is one), "cpu", "cuda", "cuda:N"; heading_steps: None takes
        the checkpoint's dataset.heading_steps; limits: QueryLimits (default its defaults)."""
        encoder = CrossViewEncoder.load(ckpt, "localize", device)
        # every file checked, and refused unless these weights built it: each problem names its file
        saved = open_gallery(gallery, encoder.fingerprint, ckpt, device=encoder.device)
        return cls(encoder, saved.index, saved.places, {**saved.info, "ckpt_loaded": str(ckpt)}, heading_steps,
                   limits, saved.calibration)

    def info(self) -> dict:
        """What /health and the JSON output say about the loaded model and gallery."""
        return {"ckpt": self.meta.get("ckpt_loaded"), "gallery_size": len(self.index), "dim": self.index.dim,
                "index": self.index.kind, "positions": self.places.kind, "query_view": self.view,
                "device": str(self.device), "heading_steps": self.heading_steps,
                "default_heading": self.default_heading, "limits": vars(self.limits),
                "calibration": self.calibration_info()}

    def calibration_info(self) -> dict:
        """{"calibrated": True, "condition": what queries the confidence holds for, "fitted_on"} or
        {"calibrated": False, "why": ...}."""
        record = self.calibration or {}
        if self.calibrator is None:
            info = {"calibrated": False, "why": record.get("why", "the gallery was saved without a calibration.json")}
        else:
            info = {"calibrated": True, "condition": self.calibrator.condition, "fitted_on": self.calibrator.fitted_on}
        if isinstance(self.within, str):
            info[WITHIN_5M] = {"calibrated": False, "why": self.within}
        elif self.within is not None:
            info[WITHIN_5M] = {"calibrated": True, "condition": self.within.condition,
                               "fitted_on": self.within.fitted_on}
        return info

    @property
    def default_heading(self) -> float | str:
        """The heading of a query that gives none: searched ("search") when the checkpoint was trained with an
        unknown heading, else north (0), the condition it was trained in."""
        return SEARCH if self.encoder.trained_heading_unknown else 0.0

    def calibrated_for(self, query: QuerySettings) -> bool:
        """Whether the confidence holds for a query of these settings: the heading given exactly, at the field of
        view the calibration was fitted at."""
        if self.calibrator is None:
            return False
        condition = self.calibrator.condition
        return (query.heading != SEARCH and not query.heading_prior
                and query.fov == condition.get("fov", 360.0))

    def check(self, width: int, height: int, query: QuerySettings, name: str = "the image") -> None:
        """QueryError (413) naming the limit when a W×H image of this query (as `settings` gives it) is over the
        limits: a door runs it on an image's header, before anything is decoded, and `localize` on the array
        (query.py)."""
        check_size(name, width, height, query.fov, self.encoder.canvas_shape(height, width, query.fov, self.view),
                   self.limits)

    def parse(self, **given) -> QuerySettings:
        """The settings as sent (QuerySettings' keys, e.g. fov, topk, heading: numbers or text; None: the default),
        parsed (check_settings, topk within max_topk) and made this localizer's query (`settings`): the door of a
        caller that has not parsed them itself, e.g. the service's form."""
        return self.settings(check_settings(**given, max_topk=self.limits.max_topk))

    def settings(self, query: QuerySettings) -> QuerySettings:
        """The query as this checkpoint and gallery answer it, once for all its images: `query` as its door parsed
        it (check_settings); one without a heading takes `default_heading`, refine says whether the answers are
        refined (`refines`), and abstain is refused where the answer's confidence does not hold (QueryError)."""
        query = dataclasses.replace(query)  # the caller's own stays as it gave it
        if query.heading is None:  # not given: as the checkpoint was trained
            query.heading = self.default_heading
        query.refine = query.refine and self.refines(query.fov)
        if query.abstain is not None and not self.calibrated_for(query):
            info = self.calibration_info()
            held = (f"its confidence is calibrated for {info['condition']}" if info["calibrated"] else
                    f"the gallery is uncalibrated: {info['why']}")
            raise QueryError("abstain", f"abstain={query.abstain:g} needs the answer's confidence, and {held}: "
                                        "give the image's heading (without heading_prior) at that fov, or leave "
                                        "abstain out")
        return query

    @torch.no_grad()
    def localize(self, image: np.ndarray, query: QuerySettings | None = None, *, name: str | None = None,
                 path: Path | None = None, deadline: float | None = None, **given) -> LocalizationResult:
        """image: H×W×3 uint8 RGB, a street panorama (fov 360; a full sphere when the gallery's queries are) or a
        photo covering `fov` degrees of bearing, horizon band only. query: the settings as `settings` gives them,
        trusted; left out, the settings `given` (as QuerySettings names them: fov, topk, heading, heading_prior,
        abstain, refine) are parsed by `parse`. heading: its bearing when known (degrees clockwise from north);
        "search" searches `heading_steps` candidates. path: the file, to find the image among the gallery split's
        queries (its true position then comes with the answer). deadline: a time.monotonic() past which the search
        stops with QueryError (503) instead of encoding its next candidates."""
        if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"image must be an H×W×3 uint8 RGB array, got {getattr(image, 'shape', type(image))} "
                             f"{getattr(image, 'dtype', '')}")
        if query is None:
            query = self.parse(**given)
        # the array's own size: its header, which a door checks, may have given another (an EXIF orientation turns
        # an image as it is decoded), and an array given here has none
        self.check(image.shape[1], image.shape[0], query, name or str(path or "the image"))
        calibrated = self.calibrated_for(query)
        given = None if query.heading == SEARCH else query.heading
        if query.heading_prior:
            given = headings_around(query.heading, query.heading_prior, self.heading_steps)
        inputs, headings = self.encoder.street_inputs(image, query.fov, given, self.heading_steps, view=self.view)
        descriptors = torch.cat([self._encode(inputs[start:start + CANDIDATES_PER_PASS], deadline)
                                 for start in range(0, len(inputs), CANDIDATES_PER_PASS)])
        # a row of the overall top-k is within the top-k of its own best candidate, so topk rows per candidate
        # suffice; at least 2, the confidence's margin
        scores, rows = self.index.search(descriptors, min(len(self.index), max(2, query.topk)))
        merged = self._merge(scores, rows, headings)
        best = merged[: query.topk]
        confidence = None
        if calibrated:
            features = retrieval_features([[hit["score"] for hit in merged[:2]]])
            confidence = float(self.calibrator.probability(features)[0])
        source = "search" if query.heading == SEARCH else "prior" if query.heading_prior else "given"
        answer = LocalizationResult(image=name or (str(path) if path else None), fov_deg=query.fov,
                                    heading_deg=best[0]["heading_deg"], heading_source=source,
                                    position=self._position(best[0]["row"]), topk=best, positions=self.places.kind,
                                    truth=self._truth(path, best), confidence=confidence,
                                    calibrated=calibrated,
                                    abstained=None if query.abstain is None else confidence < query.abstain)
        if query.refine:
            self._refine(answer, image)
        return answer

    def refines(self, fov: float) -> bool:
        """Whether answers are refined inside the tiles: the checkpoint has a refiner, the gallery knows its tiles'
        positions and extent, and the image is a 360° panorama (the refiner reads full panoramas)."""
        return (self.encoder.refiner is not None and fov == 360.0 and self.places.kind is not None
                and self.places.reference_extent_m is not None)

    def _refine(self, answer: LocalizationResult, image: np.ndarray) -> None:
        """Each top-k tile's refined position and heading (the top-1's is the answer's refined_position, with its
        probability map); left out when a tile's image cannot be read. The tiles are decoded a few at a time, as
        the refiner takes them (CrossViewEncoder.refine), so the memory does not grow with topk."""
        query = self.encoder.refine_query(image, answer.heading_deg, view=self.view)
        rows = [hit["row"] for hit in answer.topk]
        if self._tile_reader is None:  # where the refiner reads a margin, it finds the tiles beside each one once
            places = self.places
            self._tile_reader = self.encoder.tile_reader(lambda row: places.tile_image(places.references[row]),
                                                         places.reference_positions, places.reference_extent_m,
                                                         places.kind)
        out = self.encoder.refine(query, lambda i: self._tile_reader(rows[i]), self.places.reference_extent_m[rows])
        if out is None:
            return
        # P(within 5 m | the tile holds the camera) where it holds: the refiner searches the heading, or it is given
        within = None
        if isinstance(self.within, Calibrator) and (self.encoder.refine_config.orientation_noise_deg >= 180.0
                                        or answer.heading_source == "given"):
            within = self.within.probability(refine_features(out["mass"]))
        for i, hit in enumerate(answer.topk):
            centre = self.places.reference_positions[hit["row"]]
            east, north = out["offset_m"][i]
            where = offset_to_latlon(centre, east, north) if self.places.kind == "latlon" else centre + [east, north]
            hit["refined_position"] = {**dict(zip(POSITION_KEYS[self.places.kind], map(float, where))),
                                       "heading_deg": float((hit["heading_deg"] + out["heading_offset_deg"][i]) % 360),
                                       "mass_5m": float(out["mass"][i]),
                                       **({} if within is None else {"confidence_within_5m": float(within[i])}),
                                       **_tile_pixel(east, north, tuple(map(int, out["tile_size_px"][i])),
                                                     self.places.reference_extent_m[hit["row"]])}
        answer.refined_position = dict(answer.topk[0]["refined_position"])
        answer.probability_map = out["maps"][0]
        if answer.truth is not None and "position" in answer.truth:
            where = np.array([answer.refined_position[k] for k in POSITION_KEYS[self.places.kind]])
            truth = self.places.position_of(answer.truth["position"])
            answer.truth["refined_error_m"] = float(distance_m(truth, where, self.places.kind))

    def _encode(self, inputs: torch.Tensor, deadline: float | None) -> torch.Tensor:
        """The descriptors of a few candidate inputs, unless `deadline` has passed (QueryError 503)."""
        if deadline is not None and time.monotonic() > deadline:
            raise QueryError("max_seconds", "the query ran past its time limit before all its candidate headings "
                                            "were encoded: give the image's heading (heading=...) to skip the "
                                            "search, or send a smaller image", 503)
        return self.encoder.encode_street(inputs)

    def _merge(self, scores: torch.Tensor, rows: torch.Tensor, headings: np.ndarray) -> list[dict]:
        """Each gallery row's best score over the K candidates (K×k lists), and that candidate's heading; best
        first, the lower row first among equal scores (geoloc.eval.candidates.merge_headings)."""
        merged_scores, merged_rows, candidate = (x[0].tolist() for x in merge_headings(scores[None], rows[None]))
        return [{"rank": i + 1, **self.places.reference(row), "score": score, "heading_deg": float(headings[k])}
                for i, (score, row, k) in enumerate(zip(merged_scores, merged_rows, candidate)) if row >= 0]

    def tile(self, row) -> Path:
        """The image file of gallery row `row` (an integer, or its decimal text, in [0, gallery size)): QueryError
        404 naming the row when there is no such row or its file is not on this machine."""
        text = str(row).strip()
        if not (text.isascii() and text.isdigit()) or int(text) >= len(self.index):
            raise QueryError("row", f"tile row {str(row)[:40]!r} is not a gallery row: give an integer from 0 to "
                                    f"{len(self.index) - 1} (an answer's topk[i].row)", 404)
        path = self.places.root / self.places.references[int(text)]
        if not path.is_file():
            raise QueryError("row", f"gallery row {int(text)}'s tile {self.places.references[int(text)]} is not on "
                                    f"this machine (under the gallery's dataset root {self.places.root})", 404)
        return path

    def _position(self, row: int) -> dict | None:
        ref = self.places.reference(row)
        return {k: v for k, v in ref.items() if k not in ("row", "path")} or None

    def _rank_of(self, positive: int, best: list[dict]) -> int | None:
        """1-based rank of the true row among the answer's top-k by the scorer's rule (a tie counts in the
        query's favour), None when it is not among them."""
        if all(b["row"] != positive for b in best):
            return None
        found = rank_candidates(torch.tensor([[b["score"] for b in best]]), torch.tensor([[b["row"] for b in best]]),
                                Relevance.from_positives([positive], len(self.index)))
        return int(found.ranks[0]) + 1

    def _truth(self, path: Path | None, best: list[dict]) -> dict | None:
        """The split's record of this query: its true gallery row, position, the top-1 metre error and the rank of
        the true reference among the top-k (None when not there)."""
        line = self.places.query_of(path)
        if line is None:
            return None
        truth = {"row": line["positive"], "reference": self.places.references[line["positive"]],
                 "rank": self._rank_of(line["positive"], best)}
        where = self.places.position_of(line)
        if where is not None:
            truth["position"] = {k: line[k] for k in ("lat", "lon", "x_m", "y_m") if k in line}
            top1 = self.places.reference_positions[best[0]["row"]]
            truth["error_m"] = float(distance_m(where, top1, self.places.kind))
        return truth


def _tile_pixel(east: float, north: float, size_px, extent_m) -> dict:
    """Where a refined offset (metres east and north of a north-up tile's centre) lies in the tile's image:
    {"tile_px": [row, col], "tile_size_px": [H, W]}, which the page draws its dot at."""
    (height, width), (extent_h, extent_w) = size_px, extent_m
    row = height / 2 - float(north) * height / float(extent_h)
    col = width / 2 + float(east) * width / float(extent_w)
    return {"tile_px": [row, col], "tile_size_px": [int(height), int(width)]}
