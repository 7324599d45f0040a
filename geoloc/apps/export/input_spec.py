"""What an exported cross-view encoder expects: its input shape and the preprocessing that produced its training
images (geoloc/tasks/crossview/datasets.py), written as JSON beside the ONNX files so a deployment needs no geoloc config.

The two branches take fixed H×W (the exported graphs are specialised to them; only the batch is dynamic):
  query branch (ground view): panorama / full sphere under alignment=ipt -> IPT to aerial_size²; under polar or
      none -> resized to pano_size; a perspective photo (University-1652's drone views) -> resized to aerial_size².
  reference branch (aerial view): alignment=polar -> SAFA polar transform to pano_size; else resized to aerial_size².
"""

from __future__ import annotations

from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.transforms import IMAGENET_MEAN, IMAGENET_STD

# the query view of each built-in reader's images (RetrievalSplit.query_view); another reader's (a plug-in's) is
# taken as "panorama" unless export.py is told otherwise with query_view=
READER_QUERY_VIEWS = {"cvact": "sphere", "vigor": "sphere", "u1652": "image"}
QUERY_VIEWS = ("panorama", "sphere", "image")

NORTH = "an equirectangular panorama, north-aligned: north at the centre column (CVUSA's convention)"
SPHERE_CROP = "full-sphere panorama: keep the horizon band, rows H/4 to 3H/4 (SAFA's CVACT crop)"


def query_view_of(dataset_name: str, requested: str | None) -> str:
    """The ground-side view the query file is exported for: `requested` (export.py query_view=), or the reader's."""
    if requested in (None, "auto"):
        return READER_QUERY_VIEWS.get(dataset_name, "panorama")
    if requested not in QUERY_VIEWS:
        raise ValueError(f"query_view={requested!r} is not one of auto, {', '.join(QUERY_VIEWS)}: panorama (a street "
                         "panorama, north at the centre column), sphere (a full-sphere panorama), image (a photo)")
    return requested


def query_input(cfg: CrossViewDataConfig, view: str) -> tuple[tuple[int, int], list[str]]:
    """((H, W), geometric steps) of the query branch's input, as geoloc.tasks.crossview.transforms.align_query makes it."""
    s = cfg.aerial_size
    if view == "image":
        return (s, s), [f"resize to {s}x{s} (cv2.INTER_AREA)"]
    steps = [NORTH] + ([SPHERE_CROP] if view == "sphere" else [])
    if cfg.alignment == "ipt":
        ipt = f"inverse polar transform to {s}x{s}: geoloc.data.polar.street_to_aerial(img, ({s}, {s}))"
        return (s, s), [*steps, ipt]
    h, w = cfg.pano_size
    return (h, w), steps + [f"resize to {h}x{w} (H x W, cv2.INTER_AREA)"]


def reference_input(cfg: CrossViewDataConfig) -> tuple[tuple[int, int], list[str]]:
    """((H, W), geometric steps) of the reference branch's input, as align_reference makes it."""
    if cfg.alignment == "polar":
        h, w = cfg.pano_size
        return (h, w), [f"polar transform to {h}x{w}: geoloc.data.polar.aerial_to_polar(img, ({h}, {w}))"]
    s = cfg.aerial_size
    return (s, s), [f"resize to {s}x{s} (cv2.INTER_AREA)"]


def normalisation() -> dict:
    """The pixel encoding every branch was trained on (geoloc.tasks.crossview.transforms.to_tensor)."""
    return {"channel_order": "RGB", "scale": "divide uint8 values by 255", "mean": rounded(IMAGENET_MEAN),
            "std": rounded(IMAGENET_STD), "formula": "(pixel / 255 - mean) / std per channel, then HWC -> CHW"}


def branch_entry(file: str, view: str, hw: tuple[int, int], geometry: list[str], dim: int,
                 input_name: str, output_name: str) -> dict:
    """One file's JSON entry."""
    return {
        "file": file,
        "view": view,
        "input": {"name": input_name, "shape": ["batch", 3, *hw], "dtype": "float32", "layout": "NCHW"},
        "preprocessing": {"steps": ["decode as RGB (OpenCV reads BGR: convert it)", *geometry,
                                    "normalise: see normalisation"]},
        "output": {"name": output_name, "shape": ["batch", dim], "dtype": "float32",
                   "l2_normalised": True,
                   "similarity": "dot product (descriptors are unit length: squared distance = 2 - 2 a.b)"},
    }


def rounded(values) -> list[float]:
    """float32 constants as the decimals they were written as (0.485, not 0.48500001430511475)."""
    return [round(float(v), 6) for v in values]
