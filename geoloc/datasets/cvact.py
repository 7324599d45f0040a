"""CVACT: `ACT_data.mat` with `panoIds` and 1-based MATLAB indices `trainSet.trainInd`, `valSet.valInd` (files in
`ANU_data_small/`) and `valSetAll.valInd` (the large test split, files in `ANU_data_test/`); `utm` gives each
panorama's position in metres. Nothing is decoded."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.datasets.common import check_split, pairs_split, require_root, tile_frame
from geoloc.registry import register

CVACT_SPLITS = {"train": ("trainSet", "trainInd", "ANU_data_small"),
                "val": ("valSet", "valInd", "ANU_data_small"),
                "test": ("valSetAll", "valInd", "ANU_data_test")}
TILE_PX = 1200  # satview_polish tiles are 1200 x 1200, centred on the panorama; the release gives no ground scale


def cvact_pairs(root: str | Path, split: str) -> list[tuple[Path, Path]]:
    return cvact_index(root, split)[0]


def cvact_index(root: str | Path, split: str) -> tuple[list[tuple[Path, Path]], np.ndarray | None]:
    """The split's (street, aerial) pairs and their UTM positions (P x 2 metres, ACT_data.mat's `utm`; None when
    the file has no `utm`)."""
    from scipy.io import loadmat

    root = Path(root)
    check_split("CVACT", split, CVACT_SPLITS)
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


@register("dataset", "cvact")
def cvact(root: str, split: str) -> RetrievalSplit:
    """CVACT (ACT_data.mat; val = valSet, test = valSetAll); full-sphere panoramas, cropped to rows H/4..3H/4.
    Positions: the file's UTM (metres), when it has them."""
    require_root(root, "cvact")
    pairs, utm = cvact_index(root, split)
    return pairs_split(f"cvact/{split}", root, pairs, query_view="sphere",
                       positions=None if utm is None else ("xy", utm), tile=tile_frame(root, TILE_PX))
