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
    with open(csv_path, newline="") as f:
        for line_no, row in enumerate(csv.reader(f), start=1):
            if not row:
                continue
            if len(row) < 2:
                raise ValueError(f"{csv_path}:{line_no}: expected 'aerial,panorama,annotation', got {row}")
            pairs.append((root / row[1].strip(), root / row[0].strip()))
    if not pairs:
        raise ValueError(f"CVUSA split file {csv_path} has no rows")
    return pairs


def cvact_pairs(root: str | Path, split: str) -> list[tuple[Path, Path]]:
    from scipy.io import loadmat

    root = Path(root)
    if split not in CVACT_SPLITS:
        raise ValueError(f"CVACT has splits {sorted(CVACT_SPLITS)}, not {split!r}")
    mat_path = root / "ACT_data.mat"
    if not mat_path.is_file():
        raise FileNotFoundError(f"CVACT index {mat_path} not found. dataset.root must be the CVACT folder holding "
                                f"ACT_data.mat and ANU_data_small/ (root={root}).")
    mat = loadmat(mat_path)
    struct, field, folder = CVACT_SPLITS[split]
    try:
        ids = [str(np.asarray(p).ravel()[0]) for p in np.asarray(mat["panoIds"]).ravel()]
        index = np.asarray(mat[struct][field][0][0]).ravel().astype(np.int64) - 1  # MATLAB is 1-based
    except (KeyError, IndexError, ValueError) as err:
        raise ValueError(f"{mat_path} lacks panoIds or {struct}.{field} in the CVACT structure: {err}") from err
    if index.size and (index.min() < 0 or index.max() >= len(ids)):
        raise ValueError(f"{mat_path}: {struct}.{field} holds indices outside 1..{len(ids)} (1-based expected)")
    base = root / folder
    return [(base / "streetview" / f"{ids[i]}_grdView.jpg",
             base / "satview_polish" / f"{ids[i]}_satView_polish.jpg") for i in index]
