"""The place protocol of each dynamic-scene reader: which images are the queries, which the gallery.

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

from torch.utils.data import Dataset

from geoloc.tasks.mmdip.datasets import CarlaFourPanelDataset, DynamicDataset, EmptyCitiesDataset, panel_folder

TRAIN_SPLIT = "train"
FROM_TRAIN, FROM_GALLERY = "train split", "gallery (no train split)"


@dataclass
class PlaceProtocol:
    """Queries (items with `dynamic`, `mask`, `static`, `place`) against references (`static`, `place`, and
    `label` when `has_labels`); `vocabulary` holds the images whose `static` views train the BoW words."""

    name: str
    root: Path
    split: str | None
    image_size: tuple[int, int]
    queries: Dataset
    references: Dataset
    vocabulary: Dataset
    vocabulary_source: str
    has_labels: bool


def place_protocol(name: str, root, split: str | None, image_size) -> PlaceProtocol:
    """The protocol of reader `name` ("dynamic", "carla4" or "emptycities") on `split` of `root`."""
    root, size = Path(root), tuple(image_size)
    if name == "dynamic":
        def rows(s, roles=("reference", "query")):
            return DynamicDataset(root, s, image_size=size, roles=roles, check="off")

        return PlaceProtocol(name, root, split, size, rows(split, ("query",)), rows(split, ("reference",)),
                             rows(TRAIN_SPLIT), FROM_TRAIN, True)
    readers = {"carla4": CarlaFourPanelDataset, "emptycities": EmptyCitiesDataset}
    if name not in readers:
        raise ValueError(f"no place protocol for dataset {name!r}; choose one of dynamic, {', '.join(readers)}")
    panels = readers[name](root, split, size)  # one set of files: dynamic panels query, static panels reference
    has_train = (root / TRAIN_SPLIT).is_dir()
    vocabulary = readers[name](root, TRAIN_SPLIT, size) if has_train else panels
    return PlaceProtocol(name, root, split, size, panels, panels, vocabulary,
                         FROM_TRAIN if has_train else FROM_GALLERY, name == "carla4")


def describe(protocol: PlaceProtocol) -> str:
    folder = panel_folder(protocol.root, protocol.split) if protocol.name != "dynamic" else protocol.root
    return (f"{protocol.name} at {folder}: {len(protocol.queries)} queries (dynamic views) against "
            f"{len(protocol.references)} references (static views), vocabulary from the {protocol.vocabulary_source}")
