"""`python export.py ckpt=PATH format=onnx`: a cross-view checkpoint's two encoders as ONNX files with a dynamic
batch size, and `encoders.json` beside them saying what each file expects (CrossViewEncoder.input_spec: the
preprocessing of the query view the checkpoint records).

out/query.onnx       the query (ground-view) branch: B×3×Hq×Wq -> B×dim, L2-normalised
out/reference.onnx   the reference (aerial) branch:  B×3×Hr×Wr -> B×dim, L2-normalised
out/encoders.json    input names and shapes, preprocessing, output dim, opset, the torch-vs-onnxruntime check

A checkpoint with a refiner (docs/localisation.md) adds its two encoders, whose maps the refiner correlates:
out/refine_query.onnx      the aligned query at the refiner's side: B×3×s×s -> B×C×n×n feature maps
out/refine_reference.onnx  a tile at the refiner's side:             B×3×s×s -> B×C×n×n feature maps
                           (with refiner.margin: the tile and its margin, B×4×s'×s' -> B×C×n'×n', encoders.json's
                           "reference" entry says how the fourth channel and the margin are read)
The correlation itself (an FFT over complex numbers, which torch.onnx does not export) is written out in
encoders.json's "refiner" entry; it is geoloc.models.refiners.correlation.correlate.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from geoloc.config import ConfigError
from geoloc.tasks.crossview import CrossViewEncoder

FORMATS = ("onnx",)
FILES = {"query": "query.onnx", "reference": "reference.onnx"}
REFINER_FILES = {"query": "refine_query.onnx", "reference": "refine_reference.onnx"}
MAP_NAME = "feature_map"
SPEC_FILE = "encoders.json"
INPUT_NAME, OUTPUT_NAME = "image", "descriptor"
# a protobuf file holds at most 2 GB: a branch with more weights than this keeps them in `<file>.data` beside it
SINGLE_FILE_BYTES = 1_800_000_000
# the exported graph must reproduce torch's descriptors (unit vectors) to float32 rounding; far above it, it is wrong
CHECK_TOLERANCE = 1e-4


def export(cfg: DictConfig) -> dict:
    """export.py's work; returns what encoders.json holds. Nothing is read or written before the format, the
    exporter's packages and the output folder are checked."""
    if cfg.format not in FORMATS:
        raise ConfigError(f"format={cfg.format} is not supported; export.py writes {', '.join(FORMATS)} "
                          f"(format=onnx)")
    require_packages()
    opset = checked_opset(cfg.get("opset"))
    ckpt = Path(cfg.ckpt)
    out = Path(cfg.out) if cfg.get("out") else default_out(ckpt)
    if not cfg.get("overwrite", False):
        refuse_existing(out)
    encoder = CrossViewEncoder.load(ckpt, "export.py", device="cpu")
    # the exporter's graph passes log each step at INFO, which Hydra's job logging would print
    for name in ("onnxscript", "onnx_ir"):
        logging.getLogger(name).setLevel(logging.WARNING)
    started = time.perf_counter()
    spec = export_encoders(encoder, out, query_view=cfg.get("query_view"), opset=opset)
    spec["source"] = {"ckpt": str(ckpt), "epoch": encoder.epoch, "dataset": encoder.data.name}
    (out / SPEC_FILE).write_text(json.dumps(spec, indent=2) + "\n")
    sizes = ", ".join(f"{f} {(out / f).stat().st_size / 1e6:.1f} MB" for f in FILES.values())
    print(f"exported in {time.perf_counter() - started:.1f} s to {out}: {sizes}, {SPEC_FILE}")
    return spec


def export_encoders(encoder: CrossViewEncoder, out: Path, query_view: str | None = None,
                    opset: int | None = None) -> dict:
    """Write query.onnx and reference.onnx of `encoder` into `out`; return the spec of both. query_view: what
    query.onnx is described as taking (None or "auto": the checkpoint's). Files are written to a temp folder inside
    `out` and moved in at the end: a failed export leaves no partial file behind."""
    inputs = encoder.input_spec(query_view)
    view = inputs["query_view"]
    branches = {"query": (f"ground ({view})", inputs["query"]), "reference": ("aerial", inputs["reference"])}
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".export-", dir=out))
    try:
        spec = {}
        for name, (described, (hw, geometry)) in branches.items():
            branch = encoder.branches[name]
            example = torch.randn(2, 3, *hw, generator=torch.Generator().manual_seed(0))
            used_opset = export_branch(branch, example, tmp / FILES[name], opset)
            if opset is not None and used_opset != opset:
                raise RuntimeError(f"{FILES[name]}: torch.onnx wrote opset {used_opset}, not the opset={opset} asked "
                                   f"for; nothing was written. Choose an opset in {opset_text()}.")
            entry = branch_entry(FILES[name], described, hw, geometry, model_dim(branch, example))
            entry["checked_against_torch"] = checked(branch, tmp / FILES[name], example)
            spec[name] = entry
        if encoder.refiner is not None:
            spec["refiner"] = export_refiner(encoder, tmp, opset)
        for path in tmp.iterdir():
            os.replace(path, out / path.name)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise
    tmp.rmdir()
    data = encoder.data
    return {"format": "geoloc cross-view encoders, ONNX", "opset": used_opset,
            "exporter": f"torch.onnx.export(dynamo=True), torch {torch.__version__}",
            "dataset": {"name": data.name, "alignment": data.alignment, "aerial_size": data.aerial_size,
                        "pano_size": list(data.pano_size),
                        **({"ground_extent_m": data.ground_extent_m, "camera_height_m": data.camera_height_m}
                           if data.alignment == "ground" else {})},
            "shared_weights": bool(getattr(encoder.model, "shared", False)),
            **queries_entry(encoder, view),
            "usage": ("each image goes through its own view's file: ground images (street panoramas, drone photos) "
                      "through query.onnx, aerial images through reference.onnx; rank references by the dot "
                      "product of the descriptors. For aerial queries (University-1652 satellite -> drone) the "
                      "queries go through reference.onnx and the drone gallery through query.onnx."),
            "normalisation": inputs["normalisation"], **spec}


class _Encode(torch.nn.Module):
    """One of a refiner's encode_query / encode_reference as a module to export."""

    def __init__(self, refiner: torch.nn.Module, side: str):
        super().__init__()
        self.refiner, self.side = refiner, side

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return getattr(self.refiner, f"encode_{self.side}")(images)


def export_refiner(encoder: CrossViewEncoder, tmp: Path, opset: int | None) -> dict:
    """The refiner's two encoders into `tmp` (REFINER_FILES), each checked against torch; their spec entry."""
    side = encoder.refine_config.side(encoder.data.aerial_size)
    entry = {"name": encoder.config.refiner.get("name"), "side": side,
             "orientation_noise_deg": encoder.refine_config.orientation_noise_deg,
             "heading_bins": getattr(encoder.refiner, "heading_bins", None),
             "matching": ("log P(heading k, position) = log_softmax over (k, position) of scale x the mean dot product "
                          "of the query map's central window, turned clockwise by heading k (and drawn "
                          "query_extent_m / tile extent times larger about its centre where query_extent_m > 0), "
                          "with the tile map (and its margin, where the tile is read with one), the window's "
                          "centre on each cell corner of the tile, the mean taken over the window's cells on the "
                          "map that hold imagery (overlap 'mean') or the whole window "
                          "('window'), or ('evidence') the sum over the window's cells on the tile less "
                          "evidence_offset for each of them, over the whole window; "
                          "geoloc.models.refiners.correlation.correlate, and Refinement "
                          "(refinement.py) for the estimates read from it"),
             "overlap": getattr(encoder.refiner, "overlap", None),
             "evidence_offset": (float(encoder.refiner.evidence_offset.detach())
                                 if getattr(encoder.refiner, "evidence_offset", None) is not None else None),
             "query_extent_m": encoder.refine_config.query_extent_m,
             "scale": float(encoder.refiner.log_scale.detach().exp()) if hasattr(encoder.refiner, "log_scale") else None}
    margin, wide = encoder.refine_config.margin, encoder.refine_reference_side()
    for name, file in REFINER_FILES.items():
        module = _Encode(encoder.refiner, name).eval()
        channels, size = (4, wide) if name == "reference" and margin else (3, side)
        example = torch.randn(2, channels, size, size, generator=torch.Generator().manual_seed(1))
        if channels == 4:  # the coverage channel: 1 on imagery, 0 on a margin no tile covers
            example[:, 3] = 1.0
            example[1, 3, :, size - size // 8:] = 0.0
        export_branch(module, example, tmp / file, opset, output_name=MAP_NAME)
        entry[name] = {"file": file, "input": {"name": INPUT_NAME, "shape": ["batch", channels, size, size]},
                       "preprocessing": "as the branch of the same view, at side x side",
                       "checked_against_torch": checked(module, tmp / file, example, output_name=MAP_NAME)}
    if margin:
        entry["margin"] = margin
        entry["reference"]["preprocessing"] = (
            f"the tile with {margin} of its side of ground beyond each edge, cut from the half-overlapping tiles "
            f"beside it (geoloc.data.tile_context), at {wide} x {wide} pixels ({(wide - side) // 2} beyond "
            f"each edge of the {side}-pixel tile): the 3 colour channels as the branch of the same view, then a "
            "fourth that is 1 where a tile covers the pixel and 0 where none does; the feature map's cells with no "
            "imagery come out as zero vectors, and the correlation scores only the tile's own cell corners")
    return entry


def queries_entry(encoder: CrossViewEncoder, ground_view: str) -> dict:
    """{"queries": the view of the queries the checkpoint was validated on, the file they go through, and its
    gallery's}: an aerial view (University-1652 satellite -> drone) goes through reference.onnx and its gallery of
    ground images through query.onnx. Empty when neither the checkpoint nor its dataset can say (an old checkpoint
    exported with query_view= given, away from its data)."""
    try:
        view = encoder.query_views["val"]
    except ConfigError:
        return {}
    if view == "aerial":
        return {"queries": {"view": view, "file": FILES["reference"],
                            "gallery": {"view": ground_view, "file": FILES["query"]}}}
    return {"queries": {"view": view, "file": FILES["query"],
                        "gallery": {"view": "aerial", "file": FILES["reference"]}}}


def branch_entry(file: str, view: str, hw: tuple[int, int], geometry: list[str], dim: int) -> dict:
    """One file's JSON entry."""
    return {
        "file": file,
        "view": view,
        "input": {"name": INPUT_NAME, "shape": ["batch", 3, *hw], "dtype": "float32", "layout": "NCHW"},
        "preprocessing": {"steps": ["decode as RGB (OpenCV reads BGR: convert it)", *geometry,
                                    "normalise: see normalisation"]},
        "output": {"name": OUTPUT_NAME, "shape": ["batch", dim], "dtype": "float32",
                   "l2_normalised": True,
                   "similarity": "dot product (descriptors are unit length: squared distance = 2 - 2 a.b)"},
    }


def export_branch(branch: torch.nn.Module, example: torch.Tensor, path: Path, opset: int | None,
                  output_name: str = OUTPUT_NAME) -> int:
    """One branch to `path`, batch dimension dynamic, H and W fixed to the example's; returns the opset written.

    Exporter: torch.export (dynamo=True) with a dynamic batch Dim. The TorchScript exporter (dynamo=False) refuses
    MSAE's adaptive pooling to a size read from another map ("output_size is not constant"); torch.export traces
    it with H, W static and lowers it for any sizes (e.g. the paper's 18x18 conv5_3 map pooled to 8x8), and
    exports the timm ConvNeXt trunk too. H and W stay fixed: made dynamic, non-divisible adaptive pooling is
    lowered for the example's sizes only and gives wrong descriptors at others."""
    big = sum(t.numel() * t.element_size() for t in [*branch.parameters(), *branch.buffers()]) > SINGLE_FILE_BYTES
    # an example batch of 2: a batch of 1 would be specialised as a constant
    program = torch.onnx.export(branch, (example,), str(path), input_names=[INPUT_NAME], output_names=[output_name],
                                dynamo=True, dynamic_shapes=({0: torch.export.Dim("batch", min=1)},),
                                opset_version=opset, external_data=big, verbose=False)
    return int(program.model.opset_imports[""])


def supported_opsets() -> range | None:
    """The ONNX opsets torch.onnx.export(dynamo=True) writes itself: from torchlib's (the opset its operators are
    written in) to torch's newest. Below torchlib's it only tries onnx's version converter, which fails on these
    graphs and keeps torchlib's opset; above torch's newest, onnx's converter refuses. None when this torch does not
    say (the written opset is still checked)."""
    try:
        from torch.onnx import _constants
        from torch.onnx._internal.exporter import _constants as exporter_constants

        return range(int(exporter_constants.TORCHLIB_OPSET), int(_constants.ONNX_MAX_OPSET) + 1)
    except (ImportError, AttributeError):
        return None


def opset_text() -> str:
    span = supported_opsets()
    return f"{span.start}..{span.stop - 1} (torch {torch.__version__})" if span else "the range torch.onnx supports"


def checked_opset(opset) -> int | None:
    """`opset=` as an int in supported_opsets(), or None for the exporter's default; anything else is refused."""
    if opset is None:
        return None
    if isinstance(opset, bool) or not isinstance(opset, int):
        raise ConfigError(f"opset={opset!r} is not an integer; export.py takes opset in {opset_text()}, or no opset "
                          f"for the exporter's default")
    span = supported_opsets()
    if span is not None and opset not in span:
        raise ConfigError(f"opset={opset} is outside the opsets torch.onnx writes, {opset_text()}; nothing was "
                          f"exported. Pass opset=N with N in that range, or leave it out for the exporter's default.")
    return opset


def model_dim(branch: torch.nn.Module, example: torch.Tensor) -> int:
    with torch.no_grad():
        return int(branch(example[:1]).shape[1])


def checked(branch: torch.nn.Module, path: Path, example: torch.Tensor, output_name: str = OUTPUT_NAME) -> dict | None:
    """onnxruntime's descriptors of `example` against torch's (max abs difference); None without onnxruntime."""
    if importlib.util.find_spec("onnxruntime") is None:
        return None
    import onnxruntime

    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        expected = branch(example).numpy()
    got = session.run([output_name], {INPUT_NAME: example.numpy()})[0]
    diff = float(np.abs(got - expected).max())
    if not diff <= CHECK_TOLERANCE:
        raise RuntimeError(f"{path.name}: onnxruntime's descriptors differ from torch's by {diff:.3g} (max abs) on "
                           f"a random batch; the export is wrong, nothing was written. Please report it with the "
                           f"backbone and head config.")
    return {"max_abs_diff": diff, "batch": int(example.shape[0]), "onnxruntime": onnxruntime.__version__}


def default_out(ckpt: Path) -> Path:
    """Beside the checkpoint: outputs/.../best.pt -> outputs/.../best_onnx/."""
    return ckpt.parent / f"{ckpt.stem}_onnx"


def refuse_existing(out: Path) -> None:
    files = [*FILES.values(), *REFINER_FILES.values()]
    names = [*files, *(f + ".data" for f in files), SPEC_FILE]
    taken = [name for name in names if (out / name).exists()]
    if taken:
        raise ConfigError(f"out={out} already holds {', '.join(taken)}; nothing was exported. Choose another "
                          f"out=DIR, or pass overwrite=true to replace them.")


def require_packages() -> None:
    missing = [m for m in ("onnx", "onnxscript") if importlib.util.find_spec(m) is None]
    if missing:
        raise ImportError(f"format=onnx needs the packages {', '.join(missing)} (torch.onnx's exporter): "
                          "pip install -e '.[export]' (onnx, onnxscript, onnxruntime)")
