"""A cross-view checkpoint as the apps use it (localize.py, `geoloc serve`, export.py), and all they use of the task.

    encoder = CrossViewEncoder.load(ckpt, use="localize")              # device: auto, cpu, cuda, cuda:N
    inputs, headings = encoder.street_inputs(image, fov=360.0)          # K candidate headings, or heading=h
    query = encoder.encode_street(inputs)                              # K × dim, L2-normalised
    tile = encoder.encode_aerial(encoder.aerial_input(aerial))         # 1 × dim
    encoder.input_spec()                                               # each branch's input, in words (export)

It holds the network (eval mode, on its device), the dataset transform config the checkpoint was trained with
(`data`), the query views of the splits it was trained and validated on (recorded in the checkpoint; a checkpoint
from before the record asks its dataset's reader, never a table of dataset names), and the weights' fingerprint,
which saved galleries record. The preprocessing is the data module's own (transforms.py, heading.py), so an app's
inputs are the evaluation's.
"""

from __future__ import annotations

from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from geoloc import registry
from geoloc.config import ConfigError
from geoloc.data.tile_context import TileContext, at_side, stitched_side, tile_size
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine.device import autocast, log_cpu_precision, resolve_device
from geoloc.tasks.crossview.crossview_config import stored_precision
from geoloc.tasks.crossview.data_config import parse_dataset
from geoloc.tasks.crossview.heading import query_inputs
from geoloc.tasks.crossview.refine import matcher, offset_m, read_answer
from geoloc.tasks.crossview.refine_items import tile_input
from geoloc.tasks.crossview.refine_confidence import refiner_condition
from geoloc.tasks.crossview.input_spec import check_ground_view, normalisation, query_input, reference_input
from geoloc.tasks.crossview.transforms import align_query, align_reference, horizon_band, to_tensor
from geoloc.tasks.crossview.views import candidate_headings, canvas_columns, check_fov, view_canvas


REFINE_CHUNK = 8  # tiles per refiner pass: bounds a top-k refinement's memory whatever topk
TILES_KEPT = 64  # refiner.margin: decoded gallery tiles a localizer keeps for stitching (64 of 640 px: 79 MB)


class CrossViewEncoder:
    """model: the CrossViewModel (eval mode, on `device`); data: its CrossViewDataConfig; config: the checkpoint's
    whole config (older layouts upgraded); source: the checkpoint file; epoch: the epoch it was saved at."""

    def __init__(self, task, config: DictConfig, state: dict, source, device: torch.device):
        self.model = task.model.to(device).eval()
        # the checkpoint's refiner (fine-grained localisation inside a tile) and its RefineConfig, or None
        self.refiner = None if task.refiner is None else task.refiner.to(device).eval()
        self.refine_config = task.refine
        self.config, (self.data, self._reader) = config, parse_dataset(config.dataset)
        self.device, self.source, self.epoch = device, Path(source), state.get("epoch")
        self._recorded = dict((state.get("task_info") or {}).get("query_view") or {})
        self.run_precision = stored_precision(config)  # the run's autocast, as in training's validation
        log_cpu_precision(device, self.run_precision["cpu_precision"], str(source))

    @classmethod
    def load(cls, ckpt, use: str = "this app", device: str | None = None) -> "CrossViewEncoder":
        """The encoder of a cross-view checkpoint file; another task's checkpoint is refused, naming `use` (what
        wanted it: export.py, localize). device: None or "auto" (the GPU when there is one), "cpu", "cuda:N"."""
        from geoloc.tasks.crossview.crossview_run import restored_task, stored_config

        device = resolve_device(device)  # a bad device fails before the checkpoint is read
        state = ckpt_io.load(ckpt)
        task_name = OmegaConf.select(OmegaConf.create(state.get("config") or "{}"), "task.name") or "crossview"
        if task_name != "crossview":
            raise ConfigError(f"ckpt={ckpt} is a task={task_name} checkpoint; {use} takes cross-view checkpoints "
                              "(task=crossview) only")
        config = stored_config(state)
        return cls(restored_task(state, ckpt, config), config, state, ckpt, device)

    # ---- what it was trained on --------------------------------------------------------------------------------
    @property
    def query_views(self) -> dict[str, str]:
        """{"train": the training split's query view, "val": the validation split's} (RetrievalSplit.query_view).
        The training pairs' queries are ground images, so "train" is what the query branch takes (panorama, sphere,
        image); "val" may be "aerial" (University-1652 satellite -> drone: the queries go through the reference
        branch and the drone gallery through the query branch)."""
        return {key: self._recorded[key] if key in self._recorded else self._reader_views[key]
                for key in ("train", "val")}

    @property
    def query_view(self) -> str:
        """What the query branch takes: "panorama", "sphere" or "image"."""
        return self._recorded["train"] if "train" in self._recorded else self._reader_views["train"]

    @property
    def trained_heading_unknown(self) -> bool:
        """Whether training showed the street view at a random bearing (dataset.random_heading, or views=any_view),
        so that the apps search an unknown heading by default; otherwise it learnt north-aligned views, which a
        search turns into a harder task than the one it was trained for (docs/heading.md)."""
        views = OmegaConf.select(self.config, "views.name", default=None)
        return bool(self.data.random_heading) or views == "any_view"

    @cached_property
    def fingerprint(self) -> str:
        """The weights' fingerprint (engine/checkpoint.py), as saved galleries record it."""
        return ckpt_io.weights_fingerprint(self.model)

    @cached_property
    def refiner_condition(self) -> dict | None:
        """What the refiner's confidence must have been fitted for to hold for this refiner
        (refine_confidence.refiner_condition: its weights and test keys); None without a refiner."""
        return None if self.refiner is None else refiner_condition(self.refiner, self.refine_config)

    @cached_property
    def _reader_views(self) -> dict[str, str]:
        """A checkpoint without the record: its dataset's reader says (it reads the split lists, nothing decoded;
        the embedded synthetic data is rendered into its cache if it is not there, as evaluate.py would)."""
        data = self.data
        try:
            if data.root and not Path(data.root).expanduser().exists():
                raise FileNotFoundError(f"dataset.root={data.root} does not exist here")
            return {key: registry.build("dataset", self._reader, root=data.root, split=split).query_view
                    for key, split in (("train", "train"), ("val", data.val_split))}
        except (FileNotFoundError, ValueError, ConfigError) as err:
            raise ConfigError(f"{self.source} does not record the view of its queries (saved before checkpoints did), "
                              f"and its dataset ({data.name}) cannot be asked: {err}. Say what the query branch takes: "
                              "query_view=panorama | sphere | image") from err

    # ---- preprocessing -----------------------------------------------------------------------------------------
    def street_inputs(self, image: np.ndarray, fov: float = 360.0, heading: float | None = None,
                      steps: int | None = None, view: str | None = None) -> tuple[torch.Tensor, np.ndarray]:
        """image: H×W×3 uint8 RGB, a street view covering `fov` degrees of bearing (360: a panorama; a full sphere,
        view "sphere", is cut to its horizon band as the data module cuts it). heading: its bearing when known
        (degrees clockwise from north); None: the `steps` candidate headings 360·k/steps (default the checkpoint's
        dataset.heading_steps); an array of headings: those candidates. view: the images' query view (default the
        checkpoint's).
        -> (K×3×H×W query-branch inputs on the CPU, (K,) headings in degrees)."""
        view = self.query_view if view is None else view
        fov = check_fov(fov, "fov")
        if heading is None:
            headings = candidate_headings(steps or self.data.heading_steps)
        else:  # one known heading, or the candidates of a heading prior (views.headings_around)
            headings = np.atleast_1d(np.asarray(heading, np.float64)) % 360.0
        return query_inputs(self._street(image, fov, view), self.data, view, fov, headings), headings

    def canvas_shape(self, height: int, width: int, fov: float, view: str | None = None) -> tuple[int, float]:
        """(rows, columns) of the 360° canvas street_inputs places an H×W image of `fov` degrees on, known before
        anything is decoded or allocated: rows the horizon band's for a full sphere; columns W·360/fov (a float,
        inf for a vanishing fov)."""
        view = self.query_view if view is None else view
        fov = check_fov(fov, "fov")
        rows = self._street(np.empty((height, 0), np.uint8), fov, view).shape[0]  # no pixels: the rows alone
        return rows, canvas_columns(width, fov)

    @staticmethod
    def _street(image: np.ndarray, fov: float, view: str) -> np.ndarray:
        """The rows of the image that make the street view: a full sphere's horizon band at fov 360."""
        return horizon_band(image) if view == "sphere" and fov == 360.0 else image

    def aerial_input(self, tile: np.ndarray) -> torch.Tensor:
        """tile: H×W×3 uint8 RGB aerial image -> 1×3×H×W reference-branch input on the CPU. The data module decodes
        a JPEG tile at reduced scale where its resize allows (transforms.decode_size); a tile decoded the same way
        (geoloc.data.io.read_rgb(path, decode_size(self.data, "aerial"))) gives the gallery's input exactly."""
        return to_tensor(align_reference(tile, self.data))[None]

    def autocast(self):
        """The run's autocast on this encoder's device (engine.device.autocast), as training's validation used."""
        return autocast(self.run_precision["precision"], self.device, self.run_precision["cpu_precision"])

    @torch.no_grad()
    def encode_street(self, inputs: torch.Tensor) -> torch.Tensor:
        """B×3×H×W query-branch inputs -> B×dim float32 descriptors on the encoder's device."""
        with self.autocast():
            return self.model.query(inputs.to(self.device)).float()

    @torch.no_grad()
    def encode_aerial(self, inputs: torch.Tensor) -> torch.Tensor:
        """B×3×H×W reference-branch inputs -> B×dim float32 descriptors on the encoder's device."""
        with self.autocast():
            return self.model.reference(inputs.to(self.device)).float()

    # ---- refinement inside a tile ------------------------------------------------------------------------------
    def refine_query(self, image: np.ndarray, heading: float, view: str | None = None) -> torch.Tensor:
        """A 360° street image of bearing `heading` -> the refiner's query input on the CPU: 1×3×s×s, north up (the
        image turned back by its heading)."""
        from dataclasses import replace

        view = self.query_view if view is None else view
        side = self.refine_config.side(self.data.aerial_size)
        north_up = view_canvas(self._street(image, 360.0, view), 360.0, heading)
        return to_tensor(align_query(north_up, replace(self.data, aerial_size=side), view))[None]

    def refine_tile(self, tile: np.ndarray) -> torch.Tensor:
        """An aerial tile (H×W×3 uint8) -> the refiner's reference input on the CPU: 3×s×s; a tile with its margin
        (H'×W'×4, as tile_reader gives it where refiner.margin > 0) -> 4×s'×s'."""
        side = self.refine_config.side(self.data.aerial_size)
        return tile_input(tile if tile.shape[-1] == 3 else at_side(tile, side, self.refine_config.margin), side)

    def refine_reference_side(self) -> int:
        """The side in pixels of the refiner's reference input: the tile's, plus its margin on either side where
        refiner.margin reads one."""
        return stitched_side(self.refine_config.side(self.data.aerial_size), self.refine_config.margin)

    def tile_reader(self, read, positions, extent_m, kind: str):
        """What refine's `tile` reads for gallery row i: read(i) (H×W×3 uint8, or None where it cannot be read)
        where the refiner reads the tile alone; where it reads a margin (refiner.margin), the tile stitched with the
        ground beyond its edges from the gallery's tiles beside it (geoloc/data/tile_context.py), found by their
        positions ((N, 2) as `kind` "latlon" or "xy" says) and extent_m ((N, 2) metres)."""
        if self.refine_config is None or not self.refine_config.margin:
            return read
        # a tile and its neighbours are read together, and the top-k tiles are often neighbours themselves
        cached = lru_cache(maxsize=TILES_KEPT)(read)
        return TileContext.of_gallery(cached, positions, extent_m, kind, self.refine_config.margin).image

    def _tile_size(self, image: np.ndarray) -> tuple[int, int]:
        """The (H, W) pixels of the tile an image refine_tile takes shows (a stitched one's without its margin)."""
        if image.shape[-1] == 3:
            return image.shape[:2]
        return tuple(tile_size(n, self.refine_config.margin) for n in image.shape[:2])

    @torch.no_grad()
    def refine(self, query: torch.Tensor, tile, extent_m: np.ndarray, radius_m: float = 5.0,
               chunk: int = REFINE_CHUNK) -> dict | None:
        """The refiner's answer for one query (refine_query) in each of T tiles covering extent_m (T×2 metres,
        height and width). tile(i): tile i's image (H×W×3 uint8; with refiner.margin its stitched
        image, tile_reader), or None where it cannot be read; the tiles are
        decoded, encoded and matched `chunk` at a time, as they are consumed, so the memory does not grow with T,
        and the query's map is encoded once and turned once per query scale (the tiles are taken scale by scale;
        the answer is the one a single batch of all T gives). -> {"offset_m": T×2 (east, north) metres from each
        tile's centre, "heading_offset_deg": (T,) degrees to add to the query's heading (0 when the refiner was
        trained with a known heading), "mass": (T,) the probability within radius_m of each position (the
        refiner's own score), "maps": T×R×C the probability of each position (a lattice over the tile, edges
        included), "tile_size_px": T×2 each tile's (H, W)}, or None when a tile cannot be read."""
        if self.refiner is None:
            raise ConfigError(f"{self.source} has no refiner: train one (docs/localisation.md)")
        extent = np.asarray(extent_m, np.float64).reshape(-1, 2)
        with self.autocast():  # the maps as validation encodes them, matched in float32
            maps = self.refiner.encode_query(query.to(self.device)).float()
        candidates = self.refine_config.candidates(getattr(self.refiner, "heading_bins", 36))
        scales = self.refine_config.query_scale(extent)
        groups = ([(None, np.arange(len(extent)))] if scales is None else
                  [(scale, np.flatnonzero(scales.numpy() == scale.item())) for scale in scales.unique()])
        out = {}
        for scale, rows in groups:
            matched = matcher(self.refiner, maps, candidates, scale)
            for start in range(0, len(rows), chunk):
                part = rows[start:start + chunk]
                tiles = [tile(int(i)) for i in part]
                if any(image is None for image in tiles):
                    return None
                inputs = torch.stack([self.refine_tile(image) for image in tiles])
                with self.autocast():
                    reference_maps = self.refiner.encode_reference(inputs.to(self.device)).float()
                found = matched(reference_maps)
                metres = torch.as_tensor(extent[part], dtype=torch.float32, device=self.device)
                position, mass = read_answer(found, self.refine_config, radius_m, metres)
                answer = {"offset_m": offset_m(position.cpu().double().numpy(), extent[part]),
                          "heading_offset_deg": (found.heading().cpu().numpy()
                                                 if self.refine_config.orientation_noise_deg > 0
                                                 else np.zeros(len(part))),
                          "mass": mass.cpu().numpy(),
                          "maps": found.position_log_prob.exp().cpu().numpy(),
                          "tile_size_px": np.array([self._tile_size(image) for image in tiles])}
                for key, value in answer.items():
                    out.setdefault(key, np.zeros((len(extent), *value.shape[1:]), value.dtype))[part] = value
        return out

    # ---- export ------------------------------------------------------------------------------------------------
    @property
    def branches(self) -> dict[str, torch.nn.Module]:
        """{"query": the ground-view branch, "reference": the aerial branch} (one module when model.shared)."""
        return {"query": self.model.query, "reference": self.model.reference}

    def input_spec(self, query_view: str | None = None) -> dict:
        """What each branch takes: {"query": ((H, W), preprocessing steps), "reference": (...), "normalisation":
        the pixel encoding, "query_view": the ground view the query entry describes (default the checkpoint's)}."""
        view = check_ground_view(self.query_view if query_view in (None, "auto") else query_view)
        return {"query": query_input(self.data, view), "reference": reference_input(self.data),
                "normalisation": normalisation(), "query_view": view}

    def info(self) -> dict:
        return {"ckpt": str(self.source), "epoch": self.epoch, "dataset": self.data.name,
                "device": str(self.device)}
