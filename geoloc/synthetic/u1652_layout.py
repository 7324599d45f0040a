"""The u1652 layout: University-1652's tree, read back by geoloc.datasets.u1652.

    train/satellite/<id>/<id>.jpg                       `train` buildings
    train/drone/<id>/image-01.jpeg ... image-NN.jpeg     NN = drone_views
    test/query_satellite/<id>/<id>.jpg, test/query_drone/<id>/image-NN.jpeg          `val` buildings
    test/gallery_satellite/<id>/<id>.jpg, test/gallery_drone/<id>/image-NN.jpeg      `val` + `extra_gallery`

Building ids are 4 digits, numbered from 0001 over the train, test and extra (gallery-only) buildings. As in the
release, a test building's query and gallery images are the same files. No street or google views are rendered.
Jobs: one per building.
"""
from __future__ import annotations

from pathlib import Path

from . import layouts as LY
from .world_config import SynthConfig, U1652Options
from .drone import check_geometry, render_building

SPLIT_CODES = {"train": 1, "val": 2, "extra": 3}
FOLDERS = {  # kind -> (satellite folders, drone folders)
    "train": (("train/satellite",), ("train/drone",)),
    "val": (("test/query_satellite", "test/gallery_satellite"), ("test/query_drone", "test/gallery_drone")),
    "extra": (("test/gallery_satellite",), ("test/gallery_drone",)),
}


def check(cfg: SynthConfig, opts: U1652Options) -> None:
    check_geometry(cfg)


def jobs(opts: U1652Options, train: int, val: int) -> list:
    """(kind, index within kind, building number) per building."""
    out = []
    for kind, count in (("train", train), ("val", val), ("extra", opts.extra_gallery)):
        for k in range(count):
            out.append((kind, k, len(out) + 1))
    return out


def run(cfg: SynthConfig, opts: U1652Options, seed: int, kind: str, index: int, number: int, root: Path) -> dict:
    b = render_building(cfg, opts.drone_views, seed, SPLIT_CODES[kind], index)
    building = f"{number:04d}"
    satellite = LY.encode(b["satellite"], ".jpg", b["satellite_quality"])
    drone = [LY.encode(img, ".jpg", b["drone_quality"]) for img in b["drone"]]
    sat_folders, drone_folders = FOLDERS[kind]
    for folder in sat_folders:
        LY.write_bytes(root / folder / building / f"{building}.jpg", satellite, atomic=False)
    for folder in drone_folders:
        for v, data in enumerate(drone, 1):
            LY.write_bytes(root / folder / building / f"image-{v:02d}.jpeg", data, atomic=False)
    return {"kind": kind, "building": building}


def finish(root: Path, opts: U1652Options, jobs: list, records: dict) -> None:
    """Nothing to write: the folder tree is the index."""
