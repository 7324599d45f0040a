"""One street image in, a position and a heading out: a checkpoint's query branch against a saved gallery.

The gallery is what `python evaluate.py ckpt=... gallery.save=DIR` writes (geoloc/tasks/crossview/gallery.py and
places.py): the reference descriptors, where each reference is, and the split's queries. The heading is unknown in
general, so the image is encoded at K candidate headings on the 360° canvas (geoloc/tasks/crossview/views.py) and each
reference keeps its best-scoring candidate: the score ranks the references, the candidate is the heading estimate
(a circular correlation through the query encoder, DSM-style). `heading=` skips the search when it is known
(north-aligned panoramas such as CVUSA's are heading 0).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from geoloc.config import ConfigError
from geoloc.data.io import read_rgb
from geoloc.data.geo import distance_m
from geoloc.data.relevance import Relevance
from geoloc.eval.candidates import merge_headings, rank_candidates
from geoloc.eval.gallery import GalleryIndex
from geoloc.tasks.crossview import CrossViewEncoder, LocalizationResult, open_gallery


class Localizer:
    """A cross-view checkpoint (its CrossViewEncoder) and a saved gallery, loaded once; `localize(image)` answers
    one image with a LocalizationResult.

    `localize` only reads the model and the index, so concurrent calls are safe; on a CPU they gain nothing from
    running at once (the service serialises them)."""

    def __init__(self, encoder: CrossViewEncoder, index: GalleryIndex, places, info: dict,
                 heading_steps: int | None = None):
        self.encoder, self.index, self.places, self.meta = encoder, index, places, info
        # candidate headings of the search: as asked, else as the checkpoint's dataset config says
        self.device, self.heading_steps = encoder.device, int(heading_steps or encoder.data.heading_steps)
        self.view = info.get("query_view", "panorama")
        if self.view not in ("panorama", "sphere"):
            raise ConfigError(f"the gallery was built from {info.get('split')}, whose queries are {self.view} "
                              "images; localize takes street panoramas or limited-FoV street photos")

    @classmethod
    def load(cls, ckpt, gallery, device: str | None = None, heading_steps: int | None = None) -> "Localizer":
        """device: None or "auto" (the GPU when there is one), "cpu", "cuda", "cuda:N"; heading_steps: None takes
        the checkpoint's dataset.heading_steps."""
        encoder = CrossViewEncoder.load(ckpt, "localize", device)
        # every file checked, and refused unless these weights built it: each problem names its file
        saved = open_gallery(gallery, encoder.fingerprint, ckpt, device=encoder.device)
        return cls(encoder, saved.index, saved.places, {**saved.info, "ckpt_loaded": str(ckpt)}, heading_steps)

    def info(self) -> dict:
        """What /health and the JSON output say about the loaded model and gallery."""
        return {"ckpt": self.meta.get("ckpt_loaded"), "gallery_size": len(self.index), "dim": self.index.dim,
                "index": self.index.kind, "positions": self.places.kind, "query_view": self.view,
                "device": str(self.device), "heading_steps": self.heading_steps}

    @torch.no_grad()
    def localize(self, image: np.ndarray, fov: float = 360.0, topk: int = 5, heading: float | None = None,
                 name: str | None = None, path: Path | None = None) -> LocalizationResult:
        """image: H×W×3 uint8 RGB, a street panorama (fov 360; a full sphere when the gallery's queries are) or a
        photo covering `fov` degrees of bearing, horizon band only. heading: its bearing when known (degrees
        clockwise from north); None searches `heading_steps` candidates. path: the file, to find the image among
        the gallery split's queries (its true position then comes with the answer)."""
        if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"image must be an H×W×3 uint8 RGB array, got {getattr(image, 'shape', type(image))} "
                             f"{getattr(image, 'dtype', '')}")
        if int(topk) != topk or topk < 1:
            raise ValueError(f"topk must be an int >= 1, got {topk!r}")
        inputs, headings = self.encoder.street_inputs(image, fov, heading, self.heading_steps, view=self.view)
        descriptors = self.encoder.encode_street(inputs)
        # a row of the overall top-k is within the top-k of its own best candidate, so topk rows per candidate suffice
        scores, rows = self.index.search(descriptors, min(len(self.index), int(topk)))
        best = self._merge(scores, rows, headings)[: int(topk)]
        return LocalizationResult(image=name or (str(path) if path else None), fov_deg=float(fov),
                                  heading_deg=best[0]["heading_deg"],
                                  heading_source="search" if heading is None else "given",
                                  position=self._position(best[0]["row"]), topk=best, positions=self.places.kind,
                                  truth=self._truth(path, best))

    def _merge(self, scores: torch.Tensor, rows: torch.Tensor, headings: np.ndarray) -> list[dict]:
        """Each gallery row's best score over the K candidates (K×k lists), and that candidate's heading; best
        first, the lower row first among equal scores (geoloc.eval.candidates.merge_headings)."""
        merged_scores, merged_rows, candidate = (x[0].tolist() for x in merge_headings(scores[None], rows[None]))
        return [{"rank": i + 1, **self.places.reference(row), "score": score, "heading_deg": float(headings[k])}
                for i, (score, row, k) in enumerate(zip(merged_scores, merged_rows, candidate)) if row >= 0]

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


def read_street(path: Path) -> np.ndarray:
    """An image file as H×W×3 uint8 RGB (a clear error for a missing, truncated or non-image file)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    return read_rgb(path)

