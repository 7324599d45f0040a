"""What each branch of a cross-view network takes, in words: its input shape and the preprocessing that produced its
training images (transforms.py), so that a deployment needs no geoloc config (export.py writes it beside the ONNX
files: CrossViewEncoder.input_spec).

The two branches take fixed H×W:
  query branch (ground view): panorama / full sphere under alignment=ipt -> IPT to aerial_size² (a full sphere under
      ground -> its ground-plane projection to aerial_size²); under polar or
      none -> resized to pano_size; a perspective photo (University-1652's drone views) -> resized to aerial_size².
  reference branch (aerial view): alignment=polar -> SAFA polar transform to pano_size; else resized to aerial_size².
"""

from __future__ import annotations

from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.transforms import IMAGENET_MEAN, IMAGENET_STD, decode_size

GROUND_VIEWS = ("panorama", "sphere", "image")  # what the query branch can take (RetrievalSplit.query_view)

NORTH = "an equirectangular panorama, north-aligned: north at the centre column (CVUSA's convention)"
SPHERE_CROP = "full-sphere panorama: keep the horizon band, rows H/4 to 3H/4 (SAFA's CVACT crop)"


def check_ground_view(view: str, where: str = "query_view") -> str:
    if view not in GROUND_VIEWS:
        raise ValueError(f"{where}={view!r} is not one of {', '.join(GROUND_VIEWS)}: panorama (a street panorama, "
                         "north at the centre column), sphere (a full-sphere panorama), image (a photo)")
    return view


def query_input(cfg: CrossViewDataConfig, view: str) -> tuple[tuple[int, int], list[str]]:
    """((H, W), geometric steps) of the query branch's input, as geoloc.tasks.crossview.transforms.align_query makes it."""
    s = cfg.aerial_size
    if view == "image":
        return (s, s), [*decoded(cfg, view), f"resize to {s}x{s} (cv2.INTER_AREA)"]
    steps = [NORTH] + ([SPHERE_CROP] if view == "sphere" else [])
    if cfg.alignment == "ipt":
        ipt = f"inverse polar transform to {s}x{s}: geoloc.data.polar.street_to_aerial(img, ({s}, {s}))"
        return (s, s), [*steps, ipt]
    if cfg.alignment == "ground":
        ground = (f"ground-plane projection to {s}x{s}: geoloc.data.polar.street_to_ground(img, ({s}, {s}), "
                  f"extent_m={cfg.ground_extent_m}, camera_height_m={cfg.camera_height_m})")
        return (s, s), [*steps, ground]
    h, w = cfg.pano_size
    return (h, w), steps + [f"resize to {h}x{w} (H x W, cv2.INTER_AREA)"]


def reference_input(cfg: CrossViewDataConfig) -> tuple[tuple[int, int], list[str]]:
    """((H, W), geometric steps) of the reference branch's input, as align_reference makes it."""
    if cfg.alignment == "polar":
        h, w = cfg.pano_size
        return (h, w), [f"polar transform to {h}x{w}: geoloc.data.polar.aerial_to_polar(img, ({h}, {w}))"]
    s = cfg.aerial_size
    return (s, s), [*decoded(cfg, "aerial"), f"resize to {s}x{s} (cv2.INTER_AREA)"]


def decoded(cfg: CrossViewDataConfig, view: str) -> list[str]:
    """The decode step of an image of `view`, where it is not a plain full-size decode (transforms.decode_size)."""
    size = decode_size(cfg, view)
    if size is None:
        return []
    return [f"a JPEG is decoded at the smallest of 1/8, 1/4, 1/2 scale whose sides stay >= {size[0]}x{size[1]} "
            "(libjpeg DCT scaling: cv2.IMREAD_REDUCED_COLOR_<f>, PIL's Image.draft); other images at full size"]


def normalisation() -> dict:
    """The pixel encoding every branch was trained on (geoloc.tasks.crossview.transforms.to_tensor)."""
    return {"channel_order": "RGB", "scale": "divide uint8 values by 255", "mean": rounded(IMAGENET_MEAN),
            "std": rounded(IMAGENET_STD), "formula": "(pixel / 255 - mean) / std per channel, then HWC -> CHW"}


def rounded(values) -> list[float]:
    """float32 constants as the decimals they were written as (0.485, not 0.48500001430511475)."""
    return [round(float(v), 6) for v in values]
