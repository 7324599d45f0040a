"""The cross-view data module: any registered dataset's RetrievalSplit → training pairs and evaluation sets, with
the transforms every dataset shares (transforms.py)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from torch.utils.data import Dataset

from geoloc import registry
from geoloc.config import ConfigError
from geoloc.data.io import read_rgb
from geoloc.data.retrieval_split import PER_QUERY, PER_REFERENCE, RetrievalSplit
from geoloc.data.validate import check_files
from geoloc.engine.sampling import item_rng, split_key
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.heading import query_candidates
from geoloc.tasks.crossview.transforms import (align, align_query, align_reference, decode_size, image_tensor,
                                               jitter_draw, load_view)
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
    limit = cfg.max_train if split == "train" else cfg.max_val
    if limit and limit < out.num_queries:
        out = limited(out, limit)
    check_files(paths_to_check(out), out.root, split, cfg.check_files)
    return out


def limited(split: RetrievalSplit, n: int) -> RetrievalSplit:
    """The first n queries; a one-to-one split keeps its pairs (the first n references too)."""
    cut = PER_QUERY + (PER_REFERENCE if split.one_to_one else ())
    return replace(split, **{k: None if getattr(split, k) is None else getattr(split, k)[:n] for k in cut})


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
    item["heading"] the true heading in degrees."""

    def __init__(self, split: RetrievalSplit, cfg: CrossViewDataConfig, train: bool, augment_seed: int = 0,
                 heading_search: bool = False):
        if split.aerial_queries:
            raise ValueError(f"{split.name}: pairs need ground-side queries; this split's queries are aerial images")
        self.split, self.cfg, self.train = split, cfg, train
        self.heading_search = heading_search
        self.augment_seed = augment_seed
        self.labels = split.labels()
        self._neighbours = None

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
        street = load_view(self.split.queries[index], view, decode_size(self.cfg, view))
        aerial = read_rgb(self.split.references[label], decode_size(self.cfg, "aerial"))
        if self.heading_search:
            heading = eval_heading(index)
            candidates, _ = query_candidates(crop_view(street, self.cfg.fov, heading), self.cfg, view, self.cfg.fov,
                                             self.cfg.heading_steps)
            return {"query": candidates, "reference": image_tensor(align_reference(aerial, self.cfg)),
                    "index": index, "label": label, "heading": heading}
        rng = item_rng(self.augment_seed, key) if self.train else None
        query, reference = align(street, aerial, self.cfg, rng, view)
        item = {"query": image_tensor(query), "reference": image_tensor(reference), "index": index, "label": label}
        if rng is not None and self.cfg.color_jitter > 0:  # the query's draws, then the reference's
            item["query_jitter"] = jitter_draw(query, rng, self.cfg.color_jitter)
            item["reference_jitter"] = jitter_draw(reference, rng, self.cfg.color_jitter)
        return item


class ViewImages(Dataset):
    """One side of an evaluation split, for galleries that are not one-to-one: item {"image": 3×H×W uint8,
    "index": i} (normalised on the device, as CrossViewPairs' images). `view` is "aerial" for aerial images (the reference branch's input) or the query view of the
    split's ground-side images ("panorama", "sphere", "image")."""

    def __init__(self, paths: list[Path], view: str, cfg: CrossViewDataConfig):
        self.paths, self.view, self.cfg = list(paths), view, cfg

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, key) -> dict:
        index, _ = split_key(key)
        size = decode_size(self.cfg, self.view)
        if self.view == "aerial":
            image = align_reference(read_rgb(self.paths[index], size), self.cfg)
        else:
            street = load_view(self.paths[index], self.view, size)
            if self.view != "image":
                street = north_window(street, self.cfg.fov, 0.0)
            image = align_query(street, self.cfg, self.view)
        return {"image": image_tensor(image), "index": index}


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
    """`data` with its pairs seen at the known heading (north), one query image each: what the figures show."""
    if data.pairs is None or not data.pairs.heading_search:
        return data
    return replace(data, pairs=CrossViewPairs(data.split, data.pairs.cfg, train=False))


def build(cfg: CrossViewDataConfig, reader: dict, split: str, train: bool, augment_seed: int = 0) -> CrossViewPairs:
    """Training pairs of `split`. `augment_seed`: the run's `seed`, so a seed sweep varies the augmentation too."""
    return CrossViewPairs(read_split(cfg, reader, split), cfg, train=train, augment_seed=augment_seed)


def build_eval(cfg: CrossViewDataConfig, reader: dict, split: str) -> EvalData:
    """What validation and evaluation read of `split`: its pairs (one-to-one) or its queries and gallery apart."""
    data = read_split(cfg, reader, split)
    if data.one_to_one:
        return EvalData(data, pairs=CrossViewPairs(data, cfg, train=False, heading_search=cfg.random_heading))
    if cfg.random_heading:
        raise ConfigError(f"dataset {cfg.name!r}: evaluation with an unknown heading (dataset.random_heading=true) "
                          "scores one-to-one splits (CVUSA, CVACT, synthetic) only; evaluate this split with "
                          "dataset.random_heading=false (a known heading, north at the centre)")
    reference_view = "image" if data.aerial_queries else "aerial"
    return EvalData(data, queries=ViewImages(data.queries, data.query_view, cfg),
                    references=ViewImages(data.references, reference_view, cfg))
