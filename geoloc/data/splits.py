"""Readers for the real datasets' split files. They return (street path, aerial path) pairs; nothing is decoded.

CVUSA: `splits/{train,val}-19zl.csv`, rows `bingmap/19/N.jpg,streetview/panos/N.jpg,streetview/annotations/N.png`.
CVACT: `ACT_data.mat` with `panoIds` and 1-based MATLAB indices `trainSet.trainInd`, `valSet.valInd` (files in
`ANU_data_small/`) and `valSetAll.valInd` (the large test split, files in `ANU_data_test/`).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

CVUSA_SPLITS = {"train": "train-19zl.csv", "val": "val-19zl.csv"}
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
CVACT_SPLITS = {"train": ("trainSet", "trainInd", "ANU_data_small"),
                "val": ("valSet", "valInd", "ANU_data_small"),
                "test": ("valSetAll", "valInd", "ANU_data_test")}


def cvusa_pairs(root: str | Path, split: str) -> list[tuple[Path, Path]]:
    root = Path(root)
    if split not in CVUSA_SPLITS:
        raise ValueError(f"CVUSA has splits {sorted(CVUSA_SPLITS)}, not {split!r}")
    csv_path = root / "splits" / CVUSA_SPLITS[split]
    if not csv_path.is_file():
        raise FileNotFoundError(f"CVUSA split file {csv_path} not found. dataset.root must be the CVUSA folder "
                                f"holding bingmap/, streetview/ and splits/ (root={root}).")
    pairs = []
    try:
        with open(csv_path, newline="", encoding="utf-8-sig") as f:  # utf-8-sig: a BOM is not part of a path
            for line_no, row in enumerate(csv.reader(f), start=1):
                if not row:
                    continue
                aerial, street = _cvusa_row(row, f"{csv_path}:{line_no}")
                pairs.append((root / street, root / aerial))
    except (UnicodeDecodeError, csv.Error) as err:  # a binary or mangled file
        raise ValueError(f"CVUSA split file {csv_path} is not a readable csv ({err}); restore it from the "
                         "dataset release") from err
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


def cvact_pairs(root: str | Path, split: str) -> list[tuple[Path, Path]]:
    return cvact_index(root, split)[0]


def cvact_index(root: str | Path, split: str) -> tuple[list[tuple[Path, Path]], np.ndarray | None]:
    """The split's (street, aerial) pairs and their UTM positions (P x 2 metres, ACT_data.mat's `utm`; None when
    the file has no `utm`)."""
    from scipy.io import loadmat

    root = Path(root)
    if split not in CVACT_SPLITS:
        raise ValueError(f"CVACT has splits {sorted(CVACT_SPLITS)}, not {split!r}")
    mat_path = root / "ACT_data.mat"
    if not mat_path.is_file():
        raise FileNotFoundError(f"CVACT index {mat_path} not found. dataset.root must be the CVACT folder holding "
                                f"ACT_data.mat and ANU_data_small/ (root={root}).")
    try:
        mat = loadmat(mat_path)
    except Exception as err:  # scipy raises ValueError, TypeError, MatReadError, zlib errors... none naming the file
        raise ValueError(f"CVACT index {mat_path} is not a readable MATLAB file ({type(err).__name__}: {err}); it "
                         "is corrupt or truncated: download ACT_data.mat again") from err
    struct, field, folder = CVACT_SPLITS[split]
    try:
        ids = [str(np.asarray(p).ravel()[0]) for p in np.asarray(mat["panoIds"]).ravel()]
        index = np.asarray(mat[struct][field][0][0]).ravel().astype(np.int64) - 1  # MATLAB is 1-based
    except (KeyError, IndexError, ValueError, TypeError) as err:
        raise ValueError(f"{mat_path} lacks panoIds or {struct}.{field} in the CVACT structure: {err}") from err
    if index.size and (index.min() < 0 or index.max() >= len(ids)):
        raise ValueError(f"{mat_path}: {struct}.{field} holds indices outside 1..{len(ids)} (1-based expected)")
    base = root / folder
    pairs = [(base / "streetview" / f"{ids[i]}_grdView.jpg",
              base / "satview_polish" / f"{ids[i]}_satView_polish.jpg") for i in index]
    utm = None
    if "utm" in mat:
        utm = np.asarray(mat["utm"], np.float64)
        if utm.shape != (len(ids), 2):
            raise ValueError(f"{mat_path}: utm has shape {utm.shape}, expected ({len(ids)}, 2), one (easting, "
                             "northing) per panoId")
        utm = utm[index]
    return pairs, utm
