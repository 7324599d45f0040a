"""Place protocols: which images of a dynamic-scene reader are the queries, which the gallery. Each reader gives
its own (readers.py, `reader.place_protocol(split)`); the built-ins:

  dynamic      queries: the `query` rows of the split (dynamic views); gallery: its `reference` rows, static views
               of the same places from another pose, time and traffic. Place ids come from the split's csv.
  carla4       each file is a place: its dynamic panel is the query, its static panel the gallery entry.
  emptycities  each file is a place: dynamic panel = query, static panel = gallery entry. No labels.

What retrieval needs labels for: only `vpr.gallery_seg=label`, which codes the gallery's SPM from the ground-truth
static labels instead of segmenting the reference image. The query's SPM always codes the predicted static
segmentation M, as the method does at test time, so a reader without labels (Empty Cities) runs the same
protocol with the predicted gallery segmentation.

The BoW vocabulary is learned on the static images of the reader's training split: `train` of the dynamic
layout, ROOT/train/ of a panel reader. A panel folder with no train/ beside it learns it on the gallery's own
static images (a map known in advance), and says so in `vocabulary_source`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from torch.utils.data import Dataset

from geoloc.tasks.mmdip.datasets import panel_folder

TRAIN_SPLIT = "train"
FROM_TRAIN, FROM_GALLERY = "train split", "gallery (no train split)"


@dataclass
class PlaceProtocol:
    """Queries (items with `dynamic`, `mask`, `static`, `place`) against references (`static`, `place`, and
    `label` when `has_labels`); `vocabulary` holds the images whose `static` views train the BoW words. `folder`
    is where the split's images are read from."""

    name: str
    root: Path
    split: str | None
    image_size: tuple[int, int]
    queries: Dataset
    references: Dataset
    vocabulary: Dataset
    vocabulary_source: str
    has_labels: bool
    folder: Path


def each_file_a_place(name: str, root: Path, split: str | None, image_size, read: Callable[[str | None], Dataset],
                      has_labels: bool) -> PlaceProtocol:
    """The protocol of a folder of samples that each hold one place's dynamic and static view: each sample's
    dynamic view queries, its static view is the gallery entry. `read(split)` gives the samples of a split."""
    root = Path(root)
    samples = read(split)
    has_train = (root / TRAIN_SPLIT).is_dir()
    vocabulary = read(TRAIN_SPLIT) if has_train else samples
    return PlaceProtocol(name, root, split, tuple(image_size), samples, samples, vocabulary,
                         FROM_TRAIN if has_train else FROM_GALLERY, has_labels, panel_folder(root, split))


def describe(protocol: PlaceProtocol) -> str:
    return (f"{protocol.name} at {protocol.folder}: {len(protocol.queries)} queries (dynamic views) against "
            f"{len(protocol.references)} references (static views), vocabulary from the {protocol.vocabulary_source}")
