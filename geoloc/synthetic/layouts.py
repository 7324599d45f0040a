"""Writers for the three output layouts: file names, per-sample files and the split/index files.

- cvusa: the CVUSA subset's tree, byte-for-byte: `bingmap/19/NNNNNNN.jpg`, `streetview/panos/NNNNNNN.jpg`,
  `streetview/annotations/NNNNNNN.png`, `splits/train-19zl.csv` and `splits/val-19zl.csv` (no header), plus
  geoloc's own `positions.csv` (made-up UTM positions, as for cvact). Numbering starts at 0000001; the val rows
  follow the train rows.
- cvact: `ANU_data_small/streetview/{id}_grdView.jpg`, `ANU_data_small/satview_polish/{id}_satView_polish.jpg` and
  `ACT_data.mat` with panoIds, trainSet.trainInd, valSet.valInd, valSetAll.valInd (1-based) and utm.
- dynamic: see docs/dynamic_layout.md.
Index files and the marker are written to a temporary name and renamed, so they are never seen half-written.
Per-sample files are written in place: a sample counts as done only once its record in `.geoloc_partial/` exists
(written after its files), so a killed run re-renders, and overwrites, any sample it had not finished.
"""
from __future__ import annotations

import io
import os
import secrets
from pathlib import Path

import cv2
import numpy as np
import scipy.io

from geoloc.data.positions import POSITIONS_FILE, positions_text

CVUSA_SPLITS = {"train": "splits/train-19zl.csv", "val": "splits/val-19zl.csv"}
DYNAMIC_HEADER = "sample,place,role,x,y,yaw,sun_azimuth,sun_elevation\n"
DYNAMIC_DIRS = ("rgb_dynamic", "rgb_static", "label_static", "label_dynamic", "mask_dynamic")


def write_bytes(path: Path, data: bytes, atomic: bool = True) -> None:
    """Write a file, creating its folder on first need (trying first saves a mkdir per file). Atomic writes go
    through a temp name of this process's own, so two writers never share one."""
    target = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp") if atomic else path
    try:
        f = open(target, "wb")
    except FileNotFoundError:
        path.parent.mkdir(parents=True, exist_ok=True)
        f = open(target, "wb")
    with f:
        f.write(data)
    if atomic:
        os.replace(target, path)


def encode(img: np.ndarray, ext: str, quality: int = 95) -> bytes:
    """RGB (or single-channel) uint8 -> encoded bytes; JPEG without optimisation flags, so it is deterministic."""
    if img.ndim == 3:
        img = np.ascontiguousarray(img[..., ::-1])
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if ext == ".jpg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    ok, buf = cv2.imencode(ext, img, params)
    if not ok:
        raise RuntimeError(f"cv2 could not encode a {ext} image of shape {img.shape}")
    return buf.tobytes()


# -- cvusa ------------------------------------------------------------------------------------------------------
def cvusa_files(number: int) -> tuple[str, str, str]:
    """1-based sample number -> (aerial, panorama, annotation) paths relative to the root."""
    stem = f"{number:07d}"
    return f"bingmap/19/{stem}.jpg", f"streetview/panos/{stem}.jpg", f"streetview/annotations/{stem}.png"


def write_cvusa_sample(root: Path, number: int, pair: dict) -> None:
    a, p, l = cvusa_files(number)
    write_bytes(root / a, encode(pair["aerial"], ".jpg", pair["aerial_conditions"].jpeg_quality), atomic=False)
    write_bytes(root / p, encode(pair["pano"], ".jpg", pair["street_conditions"].jpeg_quality), atomic=False)
    write_bytes(root / l, encode(pair["pano_labels"], ".png"), atomic=False)


def write_cvusa_splits(root: Path, numbers: dict) -> None:
    for split, rel in CVUSA_SPLITS.items():
        rows = "".join(",".join(cvusa_files(n)) + "\n" for n in numbers[split])
        write_bytes(root / rel, rows.encode())
    write_cvusa_positions(root, numbers)


def write_cvusa_positions(root: Path, numbers: dict) -> None:
    """positions.csv (geoloc/data/positions.py): each place's made-up UTM position, as CVACT's layout has."""
    rows = [(cvusa_files(n)[1], *place_utm(n)) for split in ("train", "val") for n in numbers[split]]
    write_bytes(root / POSITIONS_FILE, positions_text(rows, "xy").encode())


# -- cvact ------------------------------------------------------------------------------------------------------
def cvact_id(number: int) -> str:
    """Fixed-length ids (22 characters, like the real panoIds) so loadmat gives a plain string array."""
    return f"synthetic_{number:012d}"


def cvact_files(number: int) -> tuple[str, str]:
    i = cvact_id(number)
    return f"ANU_data_small/streetview/{i}_grdView.jpg", f"ANU_data_small/satview_polish/{i}_satView_polish.jpg"


def write_cvact_sample(root: Path, number: int, pair: dict) -> None:
    g, s = cvact_files(number)
    write_bytes(root / g, encode(pair["pano"], ".jpg", pair["street_conditions"].jpeg_quality), atomic=False)
    write_bytes(root / s, encode(pair["aerial"], ".jpg", pair["aerial_conditions"].jpeg_quality), atomic=False)


def place_utm(number: int, spacing: float = 400.0) -> tuple[float, float]:
    """Distinct, far-apart UTM positions (metres, around Canberra) for independent synthetic places."""
    row, col = divmod(number - 1, 100)
    return 690000.0 + col * spacing, 6090000.0 + row * spacing


def write_cvact_mat(root: Path, numbers: dict) -> None:
    allnum = list(numbers["train"]) + list(numbers["val"])
    n_train = len(numbers["train"])
    train_ind = np.arange(1, n_train + 1, dtype=np.int64).reshape(-1, 1)  # 1-based, MATLAB style
    val_ind = np.arange(n_train + 1, len(allnum) + 1, dtype=np.int64).reshape(-1, 1)
    mat = {
        "panoIds": np.array([cvact_id(n) for n in allnum]),
        "utm": np.array([place_utm(n) for n in allnum], np.float64).reshape(-1, 2),
        "trainSet": {"trainInd": train_ind},
        "valSet": {"valInd": val_ind},
        "valSetAll": {"valInd": val_ind},
    }
    write_bytes(root / "ACT_data.mat", mat_bytes(mat, "geoloc.data.synthetic"))


def mat_bytes(mat: dict, written_by: str) -> bytes:
    """`mat` as a MATLAB 5 file (scipy). Its 116-byte header holds a creation time stamp: a fixed text naming
    `written_by` replaces it, so the same content always gives the same bytes."""
    buf = io.BytesIO()
    scipy.io.savemat(buf, mat, format="5", oned_as="column")
    data = bytearray(buf.getvalue())
    data[:116] = f"MATLAB 5.0 MAT-file, written by {written_by}".encode().ljust(116, b" ")
    return bytes(data)


# -- dynamic ----------------------------------------------------------------------------------------------------
def dynamic_stem(place: int, role: str) -> str:
    """Place p (0-based over train then val) -> sample stems 2p+1 (reference) and 2p+2 (query)."""
    return f"{2 * place + (1 if role == 'reference' else 2):07d}"


def write_dynamic_view(root: Path, stem: str, view: dict) -> None:
    for folder in DYNAMIC_DIRS:
        write_bytes(root / folder / f"{stem}.png", encode(view[folder], ".png"), atomic=False)


def dynamic_row(stem: str, place: int, view: dict) -> str:
    p, sun = view["pose"], view["conditions"].sun
    return f"{stem},{place},{view['role']},{p.x:.3f},{p.y:.3f},{p.yaw:.2f},{sun.azimuth:.2f},{sun.elevation:.2f}\n"


def write_dynamic_splits(root: Path, rows: dict) -> None:
    for split in ("train", "val"):
        write_bytes(root / "splits" / f"{split}.csv", (DYNAMIC_HEADER + "".join(rows[split])).encode())
