"""The cross-view data module: any registered dataset's RetrievalSplit → training pairs and evaluation sets, with
the transforms every dataset shares (transforms.py)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from geoloc import registry
from geoloc.config import ConfigError
from geoloc.data.decoded import DecodedImages
from geoloc.data.io import read_rgb
from geoloc.data.retrieval_split import PER_QUERY, PER_REFERENCE, RetrievalSplit
from geoloc.data.tile_context import TileContext
from geoloc.data.validate import check_files
from geoloc.engine.sampling import item_rng, split_key
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.heading import query_candidates
import geoloc.tasks.crossview.view_pairs  # noqa: F401  (the query_views kind that build() builds)
from geoloc.tasks.crossview.refine import RefineConfig
from geoloc.tasks.crossview.refine_items import eval_offset, refine_item, tile_input
from geoloc.tasks.crossview.transforms import (align, align_query, align_reference, augment, decode_size,
                                                image_tensor, jitter_draw, load_view, to_tensor)
from geoloc.tasks.crossview.views import crop_view, eval_heading, north_window

NEIGHBOURS = 128  # GPS neighbours listed per training pair (Sample4Geo's neighbour_range)


def read_split(cfg: CrossViewDataConfig, reader: dict, split: str) -> RetrievalSplit:
    """The RetrievalSplit `split` that the `reader` section (config.parse_dataset) names, with the dataset's limits
    and file checks."""
    out = registry.build("dataset", reader, root=cfg.root, split=split)
    if not isinstance(out, RetrievalSplit):
        raise TypeError(f"dataset {cfg.name!r}: its reader returned {type(out).__name__}, not a RetrievalSplit "
                        "(docs/extending.md)")
    if out.query_view in ("image", "aerial") and (cfg.alignment != "none" or cfg.joint_flip_rotate
                                                   or cfg.rotation_deg > 0 or cfg.limited_view):
        raise ConfigError(f"dataset {cfg.name!r} has photo queries (e.g. drone views): polar alignment, the joint "
                          "flip/rotate and rotation of panoramas and the panorama field of view / heading do not "
                          "apply; set dataset.alignment=none dataset.joint_flip_rotate=false dataset.rotation_deg=0 "
                          "dataset.fov=360 dataset.random_heading=false")
    if cfg.alignment == "ground" and out.query_view != "sphere":
        raise ConfigError(f"dataset {cfg.name!r} has {out.query_view!r} queries: dataset.alignment=ground projects "
                          "the horizon band of a full-sphere panorama (VIGOR's; elevations +45° to -45°), whose "
                          "vertical angles it knows; use dataset.alignment=ipt")
    if out.query_view in ("panorama", "sphere") and cfg.aerial_rotation_deg > 0:
        raise ConfigError(f"dataset {cfg.name!r} has panorama queries: dataset.aerial_rotation_deg turns the tile "
                          "alone, which breaks its north alignment with the panorama; set "
                          "dataset.aerial_rotation_deg=0 (dataset.joint_flip_rotate turns both consistently)")
    if split == "train" and cfg.calibration_holdout:  # the held-out queries are never trained on
        out = rows_of(out, np.setdiff1d(np.arange(out.num_queries), holdout_rows(out.num_queries, _holdout(cfg, out))))
    limit = cfg.max_train if split == "train" else cfg.max_val
    if limit and limit < out.num_queries:
        out = limited(out, limit)
    check_files(paths_to_check(out), out.root, split, cfg.check_files)
    return out


def limited(split: RetrievalSplit, n: int) -> RetrievalSplit:
    """The first n queries; a one-to-one split keeps its pairs (the first n references too)."""
    return rows_of(split, range(n))


def rows_of(split: RetrievalSplit, rows) -> RetrievalSplit:
    """The queries `rows` (ascending) of `split`; a one-to-one split keeps its pairs (those references too, pair i
    of the result holding reference i)."""
    rows = np.asarray(list(rows), dtype=np.int64)
    cut = PER_QUERY + (PER_REFERENCE if split.one_to_one else ())

    def take(values):
        return [values[i] for i in rows] if isinstance(values, list) else values[rows]

    out = {k: None if getattr(split, k) is None else take(getattr(split, k)) for k in cut}
    if split.one_to_one:
        out["positives"] = np.arange(len(rows))
    return replace(split, **out)


def holdout_rows(num_queries: int, n: int) -> np.ndarray:
    """The n query rows dataset.calibration_holdout keeps out of training: spread evenly over the split (row
    floor((i + 1) Q / n) - 1 for i < n, the last row among them), so that a split listed city by city (VIGOR) or
    place by place gives held-out queries of every part of it, as its test queries are."""
    return (np.arange(1, n + 1) * num_queries) // n - 1


def _holdout(cfg: CrossViewDataConfig, train: RetrievalSplit) -> int:
    if cfg.calibration_holdout >= train.num_queries:
        raise ConfigError(f"dataset.calibration_holdout={cfg.calibration_holdout} keeps every one of the "
                          f"{train.num_queries} train queries of {train.name} out of training: give fewer (a tenth "
                          "to a quarter of them), or 0 for none")
    return cfg.calibration_holdout


def held_out(split: RetrievalSplit, n: int) -> RetrievalSplit:
    """The n queries of `split` that dataset.calibration_holdout keeps out of training (holdout_rows); a one-to-one
    split keeps its pairs."""
    return rows_of(split, holdout_rows(split.num_queries, n))


def holdout_rule(held: RetrievalSplit, use: str) -> str:
    """The record of how a calibrator's queries were chosen (held_out), and `use`: what was done with them."""
    return (f"{held.num_queries} queries spread over {held.name} (dataset.calibration_holdout), kept out of "
            f"training, {use}")


def paths_to_check(split: RetrievalSplit) -> list[Path]:
    if split.one_to_one:  # pair by pair, as the one-to-one readers list them
        return [p for pair in zip(split.queries, split.references) for p in pair]
    return [*split.queries, *split.references]


class CrossViewPairs(Dataset):
    """Training (and one-to-one validation) pairs: item i is query i with its positive reference.

    Item: {"query": 3×Hq×Wq uint8 (street, aligned), "reference": 3×Hr×Wr uint8 (aerial), "index": i (position in
    the split), "label": the positive reference's index (the place: queries of one place share it)}, and in
    training with dataset.color_jitter > 0 "query_jitter" / "reference_jitter": each image's jitter draws (4,)
    float64 (transforms.jitter_draw). transforms.normalised turns a batch of them into the branches' float input,
    on the device (CrossViewTask.on_after_batch_transfer). Keys may be ints or (index, epoch) pairs.
    `augment_seed` (the run's top-level `seed`) seeds the train-time augmentation per (seed, epoch, index).

    `heading_search` (evaluation with dataset.random_heading): query i is seen at heading eval_heading(i) with
    dataset.fov, and item["query"] is its K×3×H×W candidate inputs (heading 360·k/K each, geoloc/tasks/crossview/views.py),
    item["heading"] the true heading in degrees.

    `views` (training only; geoloc/tasks/crossview/view_pairs.py): a query_views object that makes the query's
    canvas from the augmented panorama in place of dataset.fov / random_heading, and extra views of it, given as
    item["query_views"]: V×3×Hq×Wq. None: one query, as the dataset config says."""

    def __init__(self, split: RetrievalSplit, cfg: CrossViewDataConfig, train: bool, augment_seed: int = 0,
                 heading_search: bool = False, views=None, refine: RefineConfig | None = None):
        if split.aerial_queries:
            raise ValueError(f"{split.name}: pairs need ground-side queries; this split's queries are aerial images")
        self.split, self.cfg, self.train = split, cfg, train
        self.heading_search = heading_search
        self.augment_seed = augment_seed
        self.views = views if train else None
        self.refine = refine  # a RefineConfig: items carry the refiner's inputs and truth (refine.py)
        self.labels = split.labels()
        self._neighbours = None
        # the tiles' TileContext where refine.margin reads them with a margin: their neighbours found once, here,
        # not in each loader worker
        self.context = None if refine is None else TileContext.of(split, refine.margin)
        self.decoded = DecodedImages(cfg.cache_decoded and train)  # dataset.cache_decoded (geoloc/data/decoded.py)

    def __len__(self) -> int:
        return self.split.num_queries

    @property
    def neighbours(self) -> np.ndarray | None:
        """(N, k) the other pairs nearest by GPS, nearest first, for the GPS samplers; None without positions."""
        if self.split.query_latlon is None:
            return None
        if self._neighbours is None:
            from geoloc.data.neighbours import gps_neighbour_lists

            k = min(NEIGHBOURS, len(self) - 1)
            self._neighbours = gps_neighbour_lists(self.split.query_latlon, k, self.labels)
        return self._neighbours

    def __getitem__(self, key) -> dict:
        index, _ = split_key(key)
        label = int(self.labels[index])
        view = self.split.query_view
        street = self._decoded(self.split.queries[index], view)
        aerial = self._decoded(self.split.references[label], "aerial")
        if self.heading_search:
            heading = eval_heading(index)
            candidates, _ = query_candidates(crop_view(street, self.cfg.fov, heading), self.cfg, view, self.cfg.fov,
                                             self.cfg.heading_steps)
            return {"query": candidates, "reference": image_tensor(align_reference(aerial, self.cfg)),
                    "index": index, "label": label, "heading": heading}
        rng = item_rng(self.augment_seed, key) if self.train else None
        if self.views is not None:
            return self._with_views(street, aerial, rng, index, label)
        if self.refine is not None:
            return self._refine_item(index, label, street, rng)
        query, reference = align(street, aerial, self.cfg, rng, view)
        return self._images({"query": query, "reference": reference}, rng, index=index, label=label)

    def _decoded(self, path: Path, view: str) -> np.ndarray:
        """The image at `path` decoded as a `view` (kept after the first read with dataset.cache_decoded)."""
        size = decode_size(self.cfg, view)
        return self.decoded.get((path, size), lambda: load_view(path, view, size))

    def _images(self, images: dict, rng, **item) -> dict:
        """`item` with `images` (H×W×3 uint8, or lists of them, stacked) as uint8 tensors, and, in training with
        dataset.color_jitter, each image's jitter draw under `<key>_jitter`, drawn in the order given."""
        for key, image in images.items():
            item[key] = (torch.stack([image_tensor(i) for i in image]) if isinstance(image, list)
                         else image_tensor(image))
        if rng is not None and self.cfg.color_jitter > 0:
            for key, image in images.items():
                item[f"{key}_jitter"] = (
                    np.stack([jitter_draw(i, rng, self.cfg.color_jitter) for i in image]) if isinstance(image, list)
                    else jitter_draw(image, rng, self.cfg.color_jitter))
        return item

    def _with_views(self, street, aerial, rng, index: int, label: int) -> dict:
        street, aerial = augment(street, aerial, self.cfg, rng)
        main, extras = self.views(street, rng)
        view = self.split.query_view
        return self._images({"query": align_query(main, self.cfg, view), "reference": align_reference(aerial, self.cfg),
                             "query_views": [align_query(v, self.cfg, view) for v in extras]}, rng,
                            index=index, label=label)

    def _refine_item(self, index: int, label: int, street: np.ndarray, rng) -> dict:
        """The pair as the refiner sees it (refine_items.refine_item), with the retrieval inputs of the same view."""
        item = refine_item(self.split, index, street, self.cfg, self.refine, rng, self.context)
        query = align_query(item.pop("street"), self.cfg, self.split.query_view)
        reference = align_reference(item.pop("aerial"), self.cfg)
        return self._images({"query": query, "reference": reference}, rng, index=index, label=label, **item)


class ViewImages(Dataset):
    """One side of an evaluation split, for galleries that are not one-to-one: item {"image": 3×H×W uint8,
    "index": i} (normalised on the device, as CrossViewPairs' images). `view` is "aerial" for aerial images (the
    reference branch's input) or the query view of the split's ground-side images ("panorama", "sphere", "image").

    `heading_search` (ground-side panoramas under dataset.random_heading): image i is seen at heading
    eval_heading(i) with dataset.fov, item["image"] is its K×3×H×W candidate inputs and item["heading"] the true
    heading in degrees, as CrossViewPairs gives them."""

    def __init__(self, paths: list[Path], view: str, cfg: CrossViewDataConfig, heading_search: bool = False,
                 refine: RefineConfig | None = None, context: TileContext | None = None):
        self.paths, self.view, self.cfg = list(paths), view, cfg
        self.heading_search = heading_search
        self.refine = refine  # a RefineConfig: items carry "refine_image" (and a query's "refine_heading") too
        self.context = context  # tiles: with refine.margin, their TileContext (TileContext.of the split)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, key) -> dict:
        index, _ = split_key(key)
        size = decode_size(self.cfg, self.view)
        if self.view == "aerial":
            image = align_reference(read_rgb(self.paths[index], size), self.cfg)
        else:
            street = load_view(self.paths[index], self.view, size)
            if self.heading_search:
                heading = eval_heading(index)
                candidates, _ = query_candidates(crop_view(street, self.cfg.fov, heading), self.cfg, self.view,
                                                 self.cfg.fov, self.cfg.heading_steps)
                return {"image": candidates, "index": index, "heading": heading}
            if self.view != "image":
                street = north_window(street, self.cfg.fov, 0.0)
            image = align_query(street, self.cfg, self.view)
        item = {"image": image_tensor(image), "index": index}
        if self.refine is not None:
            item.update(self._refine_input(index))
        return item

    def _refine_input(self, index: int) -> dict:
        """The refiner's input: the tile at its side, or the query at its fixed test heading (refine_items.eval_offset)."""
        side = self.refine.side(self.cfg.aerial_size)
        if self.view == "aerial":
            tile = read_rgb(self.paths[index]) if self.context is None else self.context.image(index, side)
            return {"refine_image": tile_input(tile, side)}
        offset = eval_offset(index, self.refine.orientation_noise_deg)
        street = crop_view(load_view(self.paths[index], self.view), 360.0, offset)
        query = align_query(street, replace(self.cfg, aerial_size=side), self.view)
        return {"refine_image": to_tensor(query), "refine_heading": offset % 360.0}


@dataclass
class EvalData:
    """What validation reads: the split, and either its pairs (one-to-one: both views in one loader, as the
    paper's protocol encodes them) or its two sides (queries and gallery apart: VIGOR, University-1652)."""

    split: RetrievalSplit
    pairs: CrossViewPairs | None = None
    queries: ViewImages | None = None
    references: ViewImages | None = None

    def __len__(self) -> int:
        return self.split.num_queries


def known_heading(data: EvalData) -> EvalData:
    """`data` with its queries seen at the known heading (north), one query image each: what the figures show."""
    if data.pairs is not None and data.pairs.heading_search:
        return replace(data, pairs=CrossViewPairs(data.split, data.pairs.cfg, train=False))
    if data.queries is not None and data.queries.heading_search:
        return replace(data, queries=ViewImages(data.queries.paths, data.queries.view, data.queries.cfg))
    return data


def build(cfg: CrossViewDataConfig, reader: dict, split: str, train: bool, augment_seed: int = 0,
          views: dict | None = None, refine: RefineConfig | None = None) -> CrossViewPairs:
    """Training pairs of `split`. `augment_seed`: the run's `seed`, so a seed sweep varies the augmentation too.
    `views`: the query_views section (view_pairs.py; None or `single`: one query view). refine: the refiner's
    RefineConfig, or None (retrieval alone)."""
    data = read_split(cfg, reader, split)
    pairing = None if views is None else registry.build("query_views", views)
    if pairing is not None and data.query_view not in ("panorama", "sphere"):
        raise ConfigError(f"views.name={views.get('name')!r} places panorama windows at bearings; dataset "
                          f"{cfg.name!r} has {data.query_view!r} queries: use views=single")
    if pairing is not None and refine is not None:
        raise ConfigError(f"views.name={views.get('name')!r} adds query views for a retrieval loss, and the refiner "
                          "trains on the full panorama: train the refiner with views=single")
    return CrossViewPairs(data, cfg, train=train, augment_seed=augment_seed, views=pairing, refine=refine)


def calibration_data(cfg: CrossViewDataConfig, reader: dict, refine: RefineConfig | None = None) -> EvalData | None:
    """The labelled queries that fit the confidence: the dataset.calibration_holdout train queries spread over the
    split (kept out of training), at the known heading (with `refine`, also the refiner's inputs at its test headings);
    None when the checkpoint kept none."""
    if not cfg.calibration_holdout:
        return None
    train = registry.build("dataset", reader, root=cfg.root, split="train")
    split = held_out(train, _holdout(cfg, train))
    check_files(paths_to_check(split), split.root, "train", cfg.check_files)
    return eval_sets(replace(cfg, random_heading=False), split, refine)


def build_eval(cfg: CrossViewDataConfig, reader: dict, split: str, refine: RefineConfig | None = None) -> EvalData:
    """What validation and evaluation read of `split`: its pairs (one-to-one) or its queries and gallery apart."""
    data = read_split(cfg, reader, split)
    if refine is not None and cfg.limited_view:
        raise ConfigError("the refiner reads full panoramas: with refiner set, keep dataset.fov=360 and "
                          "dataset.random_heading=false (refiner.orientation_noise_deg gives an unknown heading)")
    return eval_sets(cfg, data, refine)


def eval_sets(cfg: CrossViewDataConfig, data: RetrievalSplit, refine: RefineConfig | None = None) -> EvalData:
    """The EvalData of a split already read (build_eval; a gallery padded with distractors: `padded`)."""
    if data.one_to_one:
        return EvalData(data, pairs=CrossViewPairs(data, cfg, train=False, heading_search=cfg.random_heading,
                                                   refine=refine))
    return EvalData(data, queries=ViewImages(data.queries, data.query_view, cfg, heading_search=cfg.random_heading,
                                             refine=refine),
                    references=reference_images(data, cfg, refine))


def reference_images(split: RetrievalSplit, cfg: CrossViewDataConfig, refine: RefineConfig | None = None) -> ViewImages:
    """The gallery side of `split` as ViewImages (with `refine`, the refiner's inputs too: each tile with its margin
    where refine.margin asks for one)."""
    reference_view = "image" if split.aerial_queries else "aerial"
    context = None if refine is None or reference_view != "aerial" else TileContext.of(split, refine.margin)
    return ViewImages(split.references, reference_view, cfg, refine=refine, context=context)


def padded(split: RetrievalSplit, distractors: list[Path]) -> RetrievalSplit:
    """`split` with `distractors` (references of other places) appended to its gallery, as University-160k pads
    University-1652's: every query keeps its relevant references, and a distractor is relevant to none. The tile
    geometry and positions are left out (they describe the split's own references only); a split whose relevance
    comes from positions (the radius rule) cannot be padded, as a distractor has none."""
    if split.relevance_radius_m is not None:
        raise ConfigError(f"{split.name}: its relevance is a radius around positions, and distractor tiles carry "
                          "none; pad the gallery of a split without the radius rule, or evaluate it without "
                          "distractors")
    if split.aerial_queries:
        raise ConfigError(f"{split.name}: its gallery holds photos, not aerial tiles; distractor tiles do not apply")
    references = [*split.references, *distractors]
    labels = {}
    if split.query_labels is not None:  # each distractor a place of its own, which no query has
        fresh = int(max(split.reference_labels.max(), split.query_labels.max())) + 1
        labels = {"query_labels": split.query_labels, "reference_labels": np.concatenate(
            [split.reference_labels, fresh + np.arange(len(distractors))])}
    return RetrievalSplit(name=f"{split.name} + {len(distractors)} distractors", root=split.root,
                          queries=split.queries, references=references, positives=split.positives,
                          semi_positives=split.semi_positives, query_view=split.query_view, **labels)
