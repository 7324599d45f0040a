"""The dynamic-scene readers that task=mmdip builds by `dataset.name` (the `mmdip_dataset` kind, declared here).

A reader factory takes the shared dataset keys it names as run-time arguments (`root`, `image_size`, `augment`,
`check_files`: config.DynamicDataConfig) and its own keys, the rest of the `dataset` section, checked against its
signature as the cross-view readers' are. It returns a reader:

    reader.root                             the folder it reads
    reader.has_labels                       static segmentation labels: training and phase-1 scores need them
    reader.split(split, train, seed)        a Dataset of dicts: dynamic, static, mask, index [, label, place]
    reader.place_protocol(split)            which images query, which are the gallery (protocol.py)
    reader.class_fractions(split, force)    eq. 1's r_c of the split's labels (datasets.class_fractions)

`train` turns on the reader's augmentation, seeded by the run's `seed`. Built-ins: dynamic (the synthetic layout,
generated on first use when root is null), carla4 (the authors' 4-panel PNGs), emptycities (3 panels, no labels).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from torch.utils.data import Dataset

from geoloc import registry
from geoloc.config import ConfigError
from geoloc.tasks.mmdip.mmdip_config import DynamicDataConfig
from geoloc.tasks.mmdip.datasets import (CarlaFourPanelDataset, DynamicDataset, EmptyCitiesDataset, carla4_label_maps,
                                         class_fractions, dynamic_label_maps)
from geoloc.tasks.mmdip.protocol import FROM_TRAIN, TRAIN_SPLIT, PlaceProtocol, each_file_a_place

RUNTIME = ("root", "image_size", "augment", "check_files")
registry.declare("mmdip_dataset", section="dataset", runtime=RUNTIME)


class DynamicLayout:
    """The synthetic `dynamic` layout (docs/dynamic_layout.md): rows of splits/<split>.csv, a reference and a query
    view of each place."""

    has_labels = True

    def __init__(self, root: Path, image_size, augment: bool, check_files: str):
        self.root, self.image_size, self.augment, self.check_files = root, image_size, augment, check_files

    def split(self, split: str, train: bool = False, seed: int = 0) -> Dataset:
        return DynamicDataset(self.root, split, self.image_size, augment=train and self.augment, seed=seed,
                              check=self.check_files)

    def place_protocol(self, split: str) -> PlaceProtocol:
        size = tuple(self.image_size)

        def rows(s, roles=("reference", "query")):
            return DynamicDataset(self.root, s, image_size=size, roles=roles, check="off")

        return PlaceProtocol("dynamic", self.root, split, size, rows(split, ("query",)), rows(split, ("reference",)),
                             rows(TRAIN_SPLIT), FROM_TRAIN, True, self.root)

    def class_fractions(self, split: str = TRAIN_SPLIT, force: bool = False) -> list[float]:
        return class_fractions(self.root, split, dynamic_label_maps(self.root, split), force)


class PanelFolder:
    """A folder of multi-panel images, each its own place (ROOT/<split>/ when it exists, else ROOT): carla4 and
    emptycities. `open_split(split, train, seed)` reads a split; `label_maps` is None without labels."""

    def __init__(self, name: str, root: Path, image_size, open_split: Callable[[str | None, bool, int], Dataset],
                 label_maps: Callable | None = None):
        self.name, self.root, self.image_size = name, root, image_size
        self.open_split, self.label_maps = open_split, label_maps
        self.has_labels = label_maps is not None

    def split(self, split: str | None, train: bool = False, seed: int = 0) -> Dataset:
        return self.open_split(split, train, seed)

    def place_protocol(self, split: str | None) -> PlaceProtocol:
        return each_file_a_place(self.name, self.root, split, self.image_size, lambda s: self.open_split(s, False, 0),
                                 self.has_labels)

    def class_fractions(self, split: str = TRAIN_SPLIT, force: bool = False) -> list[float]:
        if self.label_maps is None:
            raise ConfigError(f"dataset={self.name} has no labels: it is for evaluation only (evaluate.py ckpt=...)")
        return class_fractions(self.root, split, self.label_maps(self.root, split), force)


@registry.register("mmdip_dataset", "dynamic")
def dynamic(root: str | None, image_size, augment: bool, check_files: str, preset: str = "dynamic_small",
            train_size: int = 200, val_size: int = 100, view_size: int | None = 128, seed: int = 0,
            workers: int = 2) -> DynamicLayout:
    """The layout at `root`; with none, the one the other keys describe (train_size / val_size places, two views
    each, rendered at view_size px, null = the preset's; `seed` picks the world), generated on first use into
    $GEOLOC_CACHE by `workers` processes."""
    if not root:
        from geoloc import synthetic

        root = synthetic.default_cache() / (f"dynamic-{preset}-{view_size or 'preset'}px-{train_size}-{val_size}"
                                            f"-seed{seed}")
        root = synthetic.ensure_dataset("dynamic", root, preset=preset, train=train_size, val=val_size, seed=seed,
                                        workers=workers, view_size=view_size)
    return DynamicLayout(Path(root).expanduser(), image_size, augment, check_files)


@registry.register("mmdip_dataset", "carla4")
def carla4(root: str | None, image_size, augment: bool) -> PanelFolder:
    """The authors' release: dynamic RGB | dynamic seg | static RGB | static seg (CARLA 0.8 tags)."""
    root = _required(root, "carla4")

    def open_split(split, train, seed):
        return CarlaFourPanelDataset(root, split, image_size, augment=train and augment, seed=seed)

    return PanelFolder("carla4", root, image_size, open_split, carla4_label_maps)


@registry.register("mmdip_dataset", "emptycities")
def emptycities(root: str | None, image_size) -> PanelFolder:
    """Empty Cities (Bescos et al.): dynamic | static | dynamic mask, 800 x 600 each; no labels."""
    root = _required(root, "emptycities")
    return PanelFolder("emptycities", root, image_size, lambda split, train, seed: EmptyCitiesDataset(root, split,
                                                                                                      image_size))


emptycities.evaluation_only = True  # a reader without labels says so: training on it is refused at start-up


def build_reader(cfg: DynamicDataConfig):
    """The reader `dataset.name` names (the synthetic layout is generated here on first use)."""
    return registry.build("mmdip_dataset", cfg.reader_section(), root=cfg.root, image_size=cfg.image_size,
                          augment=cfg.augment, check_files=cfg.check_files)


def load_class_fractions(root, fmt: str = "dynamic", split: str = TRAIN_SPLIT, force: bool = False) -> list[float]:
    """The class fractions of `split` of the reader `fmt` at `root` (data_prep/class_fractions.py)."""
    reader = registry.build("mmdip_dataset", {"name": fmt}, root=str(root), image_size=None, augment=False,
                            check_files="off")
    return reader.class_fractions(split, force)


def _required(root: str | None, name: str) -> Path:
    if not root:
        raise ConfigError(f"dataset={name} needs dataset.root=/path/to/the/images")
    return Path(root).expanduser()
