"""University-1652 (Zheng et al., ACM MM 2020) in its released layout -> RetrievalSplit. Nothing is decoded here.

    ROOT/train/{satellite,drone,street,google}/<building>/<image>
    ROOT/test/{query_drone,gallery_satellite,query_satellite,gallery_drone,query_street,gallery_street}/<building>/

Directions: drone_to_satellite (test: query_drone against gallery_satellite) and satellite_to_drone (test:
query_satellite against gallery_drone). The train split pairs each image of one view with the images of the
other view of its building (train/drone and train/satellite). Labels are the building ids (the folder names, as
integers); every reference of the query's building is relevant, and `positives` is the first of them. Buildings
are read in sorted order, images in sorted name order. The test galleries hold buildings that no query shows
(distractors); a query building absent from the gallery is an error.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.datasets.common import check_split, with_view
from geoloc.registry import register

DIRECTIONS = {  # direction -> split -> (query folder, reference folder)
    "drone_to_satellite": {"train": ("train/drone", "train/satellite"),
                           "test": ("test/query_drone", "test/gallery_satellite")},
    "satellite_to_drone": {"train": ("train/satellite", "train/drone"),
                           "test": ("test/query_satellite", "test/gallery_drone")},
}
SPLITS = ("train", "test")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


def u1652_split(root, split: str = "test", direction: str = "drone_to_satellite") -> RetrievalSplit:
    root = Path(root)
    if direction not in DIRECTIONS:
        raise ValueError(f"University-1652 direction must be one of {list(DIRECTIONS)}, got {direction!r}")
    check_split("University-1652", split, SPLITS)
    query_dir, ref_dir = (root / d for d in DIRECTIONS[direction][split])
    queries, query_labels = _images(query_dir)
    references, reference_labels = _images(ref_dir)
    first = {}
    for i, label in enumerate(reference_labels):
        first.setdefault(label, i)
    absent = sorted({label for label in query_labels if label not in first})
    if absent:
        raise ValueError(f"University-1652 {split} {direction}: {len(absent)} query building(s) of {query_dir} have "
                         f"no image in {ref_dir}, e.g. building {absent[0]:04d}; the two folders must come from the "
                         "same release")
    return RetrievalSplit(
        name=f"u1652/{direction}/{split}", root=root, queries=queries, references=references,
        positives=np.asarray([first[label] for label in query_labels], np.int64),
        query_labels=np.asarray(query_labels, np.int64), reference_labels=np.asarray(reference_labels, np.int64))


def _images(folder: Path) -> tuple[list[Path], list[int]]:
    """Every image of folder/<building>/, buildings and images in sorted order -> (paths, building ids)."""
    if not folder.is_dir():
        raise FileNotFoundError(
            f"University-1652 folder {folder} not found. dataset.root must be the University-1652 folder holding "
            "train/{satellite,drone} and test/{query_drone,gallery_satellite,query_satellite,gallery_drone}.")
    paths, labels = [], []
    for building in sorted(p for p in folder.iterdir() if p.is_dir()):
        if not building.name.isdigit():
            raise ValueError(f"University-1652 building folder {building} is not a building id (digits, like 0001)")
        images = sorted(p for p in building.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        paths += images
        labels += [int(building.name)] * len(images)
    if not paths:
        raise ValueError(f"University-1652 folder {folder} holds no images ({', '.join(IMAGE_SUFFIXES)}) in "
                         "building sub-folders")
    return paths, labels


@register("dataset", "u1652")
def u1652(root: str | None, split: str, direction: str = "drone_to_satellite", preset: str = "u1652_small",
          seed: int = 0, workers: int = 2) -> RetrievalSplit:
    """University-1652 in its released layout (module docstring); root=None renders the synthetic `u1652` layout."""
    if not root:
        from geoloc.synthetic import default_cache, ensure_dataset

        root = ensure_dataset("u1652", default_cache() / f"u1652-{preset}-seed{seed}", preset=preset, train=None,
                              val=None, seed=seed, workers=workers)
    split = "test" if split == "val" else split
    # training pairs are always drone -> satellite (the same pairs serve both directions); satellite_to_drone
    # queries are aerial images, which the reference branch encodes (RetrievalSplit.query_view "aerial")
    direction = "drone_to_satellite" if split == "train" else direction
    out = u1652_split(root, split=split, direction=direction)
    return with_view(out, "image" if direction == "drone_to_satellite" else "aerial")

