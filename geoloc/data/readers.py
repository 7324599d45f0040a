"""The registered datasets. A dataset is a reader: `reader(root, split, **config keys) -> RetrievalSplit` (paths
and which reference matches which query; nothing decoded). The cross-view data module (geoloc/data/crossview.py)
turns a split into training pairs and validation sets with the transforms every dataset shares.

root=None reads the embedded synthetic data, rendered on first use into $GEOLOC_CACHE (docs/synthetic.md).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from geoloc.config import ConfigError
from geoloc.data.positions import read_positions
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.data.splits import cvact_index, cvusa_pairs
from geoloc.data.u1652 import u1652_split
from geoloc.data.vigor import vigor_split
from geoloc.registry import register


def default_cache() -> Path:
    return Path(os.environ.get("GEOLOC_CACHE", Path.home() / ".cache" / "geoloc")) / "synthetic"


def pairs_split(name: str, root, pairs: list[tuple[Path, Path]], query_view: str = "panorama",
                positions: tuple[str, np.ndarray] | None = None) -> RetrievalSplit:
    """A one-to-one split from (street, aerial) pairs: query i matches reference i. positions: (kind, P x 2),
    kind "xy" (metres) or "latlon" (degrees), where pair i was taken; its query and reference share it."""
    where = {}
    if positions is not None:
        kind, array = positions
        where = {f"query_{kind}": array, f"reference_{kind}": array}
    return RetrievalSplit(name=name, root=Path(root), queries=[street for street, _ in pairs],
                          references=[aerial for _, aerial in pairs], positives=np.arange(len(pairs)),
                          query_view=query_view, **where)


def cvusa_layout_split(name: str, root, split: str) -> RetrievalSplit:
    """CVUSA's split files, with the optional positions.csv (geoloc/data/positions.py)."""
    pairs = cvusa_pairs(root, split)
    return pairs_split(name, root, pairs, positions=read_positions(Path(root), [street for street, _ in pairs]))


@register("dataset", "cvusa")
def cvusa(root: str, split: str) -> RetrievalSplit:
    """CVUSA's 35,532 / 8,884 subset (splits/{train,val}-19zl.csv); the panoramas are the horizon band."""
    _require_root(root, "cvusa")
    return cvusa_layout_split(f"cvusa/{split}", root, split)


@register("dataset", "cvact")
def cvact(root: str, split: str) -> RetrievalSplit:
    """CVACT (ACT_data.mat; val = valSet, test = valSetAll); full-sphere panoramas, cropped to rows H/4..3H/4.
    Positions: the file's UTM (metres), when it has them."""
    _require_root(root, "cvact")
    pairs, utm = cvact_index(root, split)
    return pairs_split(f"cvact/{split}", root, pairs, query_view="sphere",
                       positions=None if utm is None else ("xy", utm))


@register("dataset", "synthetic")
def synthetic(root: str | None, split: str, preset: str = "small", train_size: int = 1200, val_size: int = 300,
              seed: int = 0, workers: int = 2) -> RetrievalSplit:
    """The embedded default: a synthetic world in CVUSA's layout. `seed` picks the world, not the run's seed."""
    from geoloc.data.synthetic import ensure_dataset

    root = Path(root).expanduser() if root else default_cache() / f"cvusa-{preset}-{train_size}-{val_size}-seed{seed}"
    root = Path(ensure_dataset("cvusa", root, preset=preset, train=train_size, val=val_size, seed=seed,
                               workers=workers))
    return cvusa_layout_split(f"synthetic/{split}", root, split)


@register("dataset", "vigor")
def vigor(root: str | None, split: str, setting: str = "same_area", cities: list[str] | None = None,
          splits_dir: str = "splits", preset: str = "vigor_small", seed: int = 0, workers: int = 2) -> RetrievalSplit:
    """VIGOR (released layout, geoloc/data/vigor.py); root=None renders the synthetic `vigor` layout (4 cities)."""
    split = "test" if split == "val" else split  # VIGOR has no val split; its papers validate on test
    if not root:
        from geoloc.data.synthetic import ensure_dataset
        from geoloc.data.vigor import default_cities

        root = Path(ensure_dataset("vigor", default_cache() / f"vigor-{preset}-seed{seed}", preset=preset,
                                   train=None, val=None, seed=seed, workers=workers))
        if cities is None:  # a small preset renders fewer than four cities: the setting's that it has
            cities = [c for c in default_cities(setting, split) if (root / splits_dir / c).is_dir()]
    out = vigor_split(root, setting=setting, split=split, cities=cities, splits_dir=splits_dir)
    return _with_view(out, "sphere")


@register("dataset", "u1652")
def u1652(root: str | None, split: str, direction: str = "drone_to_satellite", preset: str = "u1652_small",
          seed: int = 0, workers: int = 2) -> RetrievalSplit:
    """University-1652 (geoloc/data/u1652.py); root=None renders the synthetic `u1652` layout."""
    if not root:
        from geoloc.data.synthetic import ensure_dataset

        root = ensure_dataset("u1652", default_cache() / f"u1652-{preset}-seed{seed}", preset=preset, train=None,
                              val=None, seed=seed, workers=workers)
    split = "test" if split == "val" else split
    # training pairs are always drone -> satellite (the same pairs serve both directions); satellite_to_drone
    # queries are aerial images, which the reference branch encodes (RetrievalSplit.query_view "aerial")
    direction = "drone_to_satellite" if split == "train" else direction
    out = u1652_split(root, split=split, direction=direction)
    return _with_view(out, "image" if direction == "drone_to_satellite" else "aerial")


def _with_view(split: RetrievalSplit, view: str) -> RetrievalSplit:
    from dataclasses import replace

    return replace(split, query_view=view)


def _require_root(root, name: str) -> None:
    if not root:
        raise ConfigError(f"dataset={name} needs dataset.root=/path/to/{name.upper()} (it is missing); the embedded "
                          "synthetic data is dataset=synthetic, vigor or u1652 with no root")
