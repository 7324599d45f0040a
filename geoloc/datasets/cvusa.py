"""CVUSA (the 35,532 / 8,884 subset every cross-view paper uses) and the embedded synthetic world in its layout.

`splits/{train,val}-19zl.csv`, rows `bingmap/19/N.jpg,streetview/panos/N.jpg,streetview/annotations/N.png`; an
optional `positions.csv` (geoloc's own, positions.py) says where each panorama was taken. Nothing is decoded.
"""

from __future__ import annotations

from pathlib import Path

from geoloc.data.list_files import csv_rows, refuse_repeats
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.datasets.common import check_split, pairs_split, require_root, tile_frame
from geoloc.data.positions import read_positions
from geoloc.registry import register

CVUSA_SPLITS = {"train": "train-19zl.csv", "val": "val-19zl.csv"}
TILE_PX = 750  # bingmap/19 tiles are 750 x 750, centred on the panorama; the release gives no ground scale


IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


def cvusa_pairs(root: str | Path, split: str) -> list[tuple[Path, Path]]:
    root = Path(root)
    check_split("CVUSA", split, CVUSA_SPLITS)
    csv_path = root / "splits" / CVUSA_SPLITS[split]
    if not csv_path.is_file():
        raise FileNotFoundError(f"CVUSA split file {csv_path} not found. dataset.root must be the CVUSA folder "
                                f"holding bingmap/, streetview/ and splits/ (root={root}).")
    rows = [(k, _cvusa_row(row, f"{csv_path}:{k}")) for k, row in csv_rows(csv_path, "CVUSA split file")]
    refuse_repeats(csv_path, [(street, k) for k, (_, street) in rows], "panorama")
    refuse_repeats(csv_path, [(aerial, k) for k, (aerial, _) in rows], "aerial image")
    pairs = [(root / street, root / aerial) for _, (aerial, street) in rows]
    if not pairs:
        raise ValueError(f"CVUSA split file {csv_path} has no rows")
    return pairs


def _cvusa_row(row: list[str], where: str) -> tuple[str, str]:
    """(aerial, street) relative paths of one split row; anything but two or three image paths is refused."""
    if len(row) not in (2, 3):
        raise ValueError(f"{where}: expected 'aerial,panorama,annotation' (2 or 3 columns), got {len(row)}: {row[:4]}")
    aerial, street = row[0].strip(), row[1].strip()
    for name in (aerial, street):
        path = Path(name)
        if path.is_absolute() or ".." in path.parts or path.suffix.lower() not in IMAGE_SUFFIXES:
            raise ValueError(f"{where}: {name!r} is not an image path relative to dataset.root (expected e.g. "
                             f"'bingmap/19/0000001.jpg,streetview/panos/0000001.jpg,...')")
    return aerial, street


def cvusa_layout_split(name: str, root, split: str) -> RetrievalSplit:
    """CVUSA's split files, with the optional positions.csv (geoloc/data/positions.py); the tiles' frame is the
    release's, or a synthetic tree's own (datasets/common.py tile_frame)."""
    pairs = cvusa_pairs(root, split)
    return pairs_split(name, root, pairs, positions=read_positions(Path(root), [street for street, _ in pairs]),
                       tile=tile_frame(root, TILE_PX))


@register("dataset", "cvusa")
def cvusa(root: str, split: str) -> RetrievalSplit:
    """CVUSA's 35,532 / 8,884 subset (splits/{train,val}-19zl.csv); the panoramas are the horizon band."""
    require_root(root, "cvusa")
    return cvusa_layout_split(f"cvusa/{split}", root, split)


@register("dataset", "synthetic")
def synthetic(root: str | None, split: str, preset: str = "small", train_size: int = 1200, val_size: int = 300,
              seed: int = 0, workers: int = 2, view_nuisance: float | None = None) -> RetrievalSplit:
    """The embedded default: a synthetic world in CVUSA's layout. `seed` picks the world, not the run's seed.
    view_nuisance: the strength of the nuisances drawn apart for the two views (geoloc.synthetic.nuisance); null,
    the default, draws none."""
    from geoloc.synthetic import default_cache, ensure_dataset

    check_split("the synthetic dataset (CVUSA's layout)", split, CVUSA_SPLITS)  # before rendering a world
    name = f"cvusa-{preset}-{train_size}-{val_size}-seed{seed}"
    if view_nuisance is not None:
        name += f"-nuisance{float(view_nuisance):g}"
    root = Path(root).expanduser() if root else default_cache() / name
    root = Path(ensure_dataset("cvusa", root, preset=preset, train=train_size, val=val_size, seed=seed,
                               workers=workers, view_nuisance=view_nuisance))
    return cvusa_layout_split(f"synthetic/{split}", root, split)
