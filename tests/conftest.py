"""Shared fixtures: tiny datasets on disk and composed Hydra configs."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from geoloc.launch.hydra_hooks import compose_conf
from geoloc.apps.localize.command import LocalizeConfig
from geoloc.launch.schemas import store_dataclass

store_dataclass("localize", LocalizeConfig)  # as localize.py stores it

REPO = Path(__file__).resolve().parents[1]
CONF = REPO / "geoloc" / "conf"
REALDATA = REPO.parent / "shared" / "realdata"


def write_cvusa(root: Path, n_train: int, n_val: int, aerial: int = 64, pano=(32, 128), seed: int = 0) -> Path:
    """A CVUSA-layout folder of random images (no learning signal needed, just the format)."""
    rng = np.random.default_rng(seed)
    for sub in ("bingmap/19", "streetview/panos", "streetview/annotations", "splits"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    rows = []
    for i in range(1, n_train + n_val + 1):
        name = f"{i:07d}"
        cv2.imwrite(str(root / f"bingmap/19/{name}.jpg"), rng.integers(0, 255, (aerial, aerial, 3), np.uint8))
        cv2.imwrite(str(root / f"streetview/panos/{name}.jpg"), rng.integers(0, 255, (*pano, 3), np.uint8))
        cv2.imwrite(str(root / f"streetview/annotations/{name}.png"), np.zeros(pano, np.uint8))
        rows.append(f"bingmap/19/{name}.jpg,streetview/panos/{name}.jpg,streetview/annotations/{name}.png\n")
    (root / "splits/train-19zl.csv").write_text("".join(rows[:n_train]))
    (root / "splits/val-19zl.csv").write_text("".join(rows[n_train:]))
    return root


@pytest.fixture(scope="session", autouse=True)
def checked_files_cache(tmp_path_factory):
    """The start-up checks remember passed files in a session folder, not in the user's ~/.cache/geoloc."""
    from geoloc.data import validate

    folder = tmp_path_factory.mktemp("checked")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(validate, "checked_dir", lambda: folder)
        yield folder


@pytest.fixture
def tiny_cvusa(tmp_path) -> Path:
    return write_cvusa(tmp_path / "cvusa", n_train=12, n_val=8)


TINY = [  # the paper's groups (not the CPU recipe's options), shrunk
    "backbone=vgg16", "head=msae", "loss=gms_triplet", "optim=adam",
    "dataset=cvusa", "dataset.aerial_size=32", "dataset.pano_size=[16,64]", "dataset.batch_size=4",
    "dataset.val_batch_size=4", "backbone.width=0.0625", "backbone.pretrained=false", "model.dim=16",
    "head.scale_channels=4", "head.proj_channels=4", "head.pool=2", "loss.queue_size=8",
    "trainer.num_workers=0", "trainer.progress=false", "trainer.device=cpu", "figures=false",
]


def compose_train(overrides: list[str]):
    return compose_conf("train", overrides)


def compose_evaluate(overrides: list[str]):
    return compose_conf("evaluate", overrides)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> tuple[Path, Path]:
    """(dataset root, run dir) of one finished 1-epoch TINY run, shared by a module's tests, which only read it."""
    from geoloc.launch import run

    base = tmp_path_factory.mktemp("finished")
    root = write_cvusa(base / "cvusa", n_train=12, n_val=8)
    run.train(compose_train([*TINY, f"dataset.root={root}", f"run_dir={base / 'run'}", "trainer.max_epochs=1"]))
    return root, base / "run"


def small_model(dim: int = 32, width: float = 0.125, msae: bool = True, scale_channels: int = 8,
                proj_channels: int = 8, pool: int = 4, batchnorm: bool = False, shared: bool = False):
    """A CPU-sized VGG16 + MSAE (or plain FC) Siamese built the way configs build it."""
    from geoloc.models.crossview import CrossViewModel, CrossViewModelConfig

    backbone = {"name": "vgg16", "width": width, "pretrained": False, "batchnorm": batchnorm}
    head = {"name": "msae" if msae else "fc", "proj_channels": proj_channels, "pool": pool}
    if msae:
        head["scale_channels"] = scale_channels
    return CrossViewModel(backbone, head, CrossViewModelConfig(dim=dim, shared=shared))


def tiny_task(dim: int = 8, width: float = 0.0625, batchnorm: bool = True, loss: dict | None = None,
              optim: dict | None = None):
    """A tiny CrossViewTask (VGG16-BN at 1/16 width, MSAE 4/4/2) with the given loss config (default gms_triplet)."""
    from geoloc.models.crossview import CrossViewModelConfig
    from geoloc.tasks.crossview.task import CrossViewTask

    backbone = {"name": "vgg16", "width": width, "pretrained": False, "batchnorm": batchnorm}
    head = {"name": "msae", "scale_channels": 4, "proj_channels": 4, "pool": 2}
    return CrossViewTask(CrossViewModelConfig(dim=dim), backbone, head, {"name": "gms_triplet", **(loss or {})},
                         optim or {"name": "adam"})


@pytest.fixture
def one_thread():
    # the machine is shared: several intra-op threads spin against each other and make tiny convs 100x slower
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
