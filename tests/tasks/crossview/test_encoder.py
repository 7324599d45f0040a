"""CrossViewEncoder, the apps' face of a checkpoint: the query views a checkpoint records (and, for an older one,
what its reader says, never a guess from the dataset's name), the data module's own preprocessing, the input spec,
the weights' fingerprint, and one rule for the device."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
import torch
from geoloc.config import ConfigError, to_yaml
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine.device import resolve_device
from geoloc.tasks.crossview import CrossViewEncoder
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.datasets import CrossViewPairs, ViewImages
from geoloc.tasks.crossview.input_spec import SPHERE_CROP, query_input, reference_input
from geoloc.data.io import read_rgb
from geoloc.tasks.crossview.transforms import (align_query, align_reference, decode_size, load_view, normalise,
                                               to_tensor)

from conftest import TINY, compose_train
from helpers.crossview_runs import task_of

SMALL = [t for t in TINY if not t.startswith("dataset=")]


def _checkpoint(path, overrides: list[str], views: dict | None) -> None:
    """An untrained checkpoint of the TINY network with the given dataset overrides; views=None: written before
    checkpoints recorded their query views."""
    cfg = compose_train([*SMALL, *overrides, f"run_dir={path.parent}"])
    torch.manual_seed(0)
    state = {"task": task_of(cfg).state_dict(), "config": to_yaml(cfg), "epoch": 3}
    if views is not None:
        state["task_info"] = {"query_view": views}
    ckpt_io.save_atomic(state, path)


def _u1652(root):
    """University-1652's folders with one building each (the reader lists files, nothing is decoded)."""
    for folder, name in (("train/satellite", "0001.jpg"), ("train/drone", "image-01.jpeg"),
                         ("test/query_satellite", "0002.jpg"), ("test/gallery_drone", "image-01.jpeg"),
                         ("test/query_drone", "image-01.jpeg"), ("test/gallery_satellite", "0002.jpg")):
        building = "0001" if folder.startswith("train") else "0002"
        (root / folder / building).mkdir(parents=True)
        (root / folder / building / name).write_bytes(b"")
    return root


@pytest.mark.slow
def test_a_trained_checkpoint_records_its_query_views(finished_run):
    root, run_dir = finished_run
    state = ckpt_io.load(run_dir / "best.pt")
    assert state["task_info"] == {"query_view": {"train": "panorama", "val": "panorama"}}
    encoder = CrossViewEncoder.load(run_dir / "best.pt", device="cpu")
    assert encoder.query_view == "panorama" and encoder.epoch == state["epoch"]
    assert not encoder.model.training and encoder.device == torch.device("cpu")
    task = task_of(compose_train([*TINY, f"dataset.root={root}", f"run_dir={run_dir}"]))
    ckpt_io.load_task_state(task, state, run_dir / "best.pt")
    assert encoder.fingerprint == ckpt_io.weights_fingerprint(task.model)  # what saved galleries record


def test_the_inputs_are_the_data_modules(finished_run):
    """Street inputs at a given heading equal the evaluation's query input; an aerial tile the gallery's input."""
    from geoloc.datasets.cvusa import cvusa

    root, run_dir = finished_run
    encoder = CrossViewEncoder.load(run_dir / "best.pt", device="cpu")
    pairs = CrossViewPairs(cvusa(str(root), "val"), encoder.data, train=False)
    street = cv2.cvtColor(cv2.imread(str(pairs.split.queries[2])), cv2.COLOR_BGR2RGB)
    inputs, headings = encoder.street_inputs(street, heading=0.0)
    assert headings.tolist() == [0.0] and torch.equal(inputs[0], normalise(pairs[2]["query"]))
    inputs, headings = encoder.street_inputs(street, steps=4)  # unknown heading: candidates 0, 90, 180, 270
    assert headings.tolist() == [0.0, 90.0, 180.0, 270.0] and inputs.shape[0] == 4
    # the tile as the data module decodes it (a JPEG at reduced scale where its resize allows: decode_size)
    aerial = read_rgb(pairs.split.references[2], decode_size(encoder.data, "aerial"))
    gallery = ViewImages(pairs.split.references, "aerial", encoder.data)
    assert torch.equal(encoder.aerial_input(aerial)[0], normalise(gallery[2]["image"]))
    with torch.no_grad():
        torch.testing.assert_close(encoder.encode_aerial(encoder.aerial_input(aerial)),
                                   encoder.model.reference(normalise(gallery[2]["image"][None])))


@pytest.mark.slow
def test_a_full_sphere_is_cut_to_its_horizon_band_as_the_data_module_cuts_it(tmp_path):
    _checkpoint(tmp_path / "best.pt", ["dataset=cvact", "dataset.root=/nowhere"], {"train": "sphere", "val": "sphere"})
    encoder = CrossViewEncoder.load(tmp_path / "best.pt", device="cpu")
    sphere = np.random.default_rng(0).integers(0, 255, (64, 128, 3), np.uint8)
    cv2.imwrite(str(tmp_path / "sphere.png"), cv2.cvtColor(sphere, cv2.COLOR_RGB2BGR))
    expected = to_tensor(align_query(load_view(tmp_path / "sphere.png", "sphere"), encoder.data, "sphere"))
    assert torch.equal(encoder.street_inputs(sphere, heading=0.0)[0][0], expected)


def test_the_record_is_read_not_a_guess_from_the_dataset_name(tmp_path):
    """A cvusa-configured checkpoint that recorded full-sphere queries is described as taking full spheres."""
    _checkpoint(tmp_path / "best.pt", ["dataset=cvusa", "dataset.root=/nowhere"], {"train": "sphere", "val": "sphere"})
    spec = CrossViewEncoder.load(tmp_path / "best.pt").input_spec()
    assert spec["query_view"] == "sphere" and SPHERE_CROP in spec["query"][1]


@pytest.mark.slow
def test_an_old_checkpoint_asks_its_reader(tmp_path):
    from conftest import write_cvusa

    root = write_cvusa(tmp_path / "cvusa", 2, 1)
    _checkpoint(tmp_path / "old.pt", ["dataset=cvusa", f"dataset.root={root}"], views=None)
    encoder = CrossViewEncoder.load(tmp_path / "old.pt")
    assert encoder.query_views == {"train": "panorama", "val": "panorama"}
    _checkpoint(tmp_path / "away.pt", ["dataset=cvact", f"dataset.root={tmp_path / 'gone'}"], views=None)
    away = CrossViewEncoder.load(tmp_path / "away.pt")
    with pytest.raises(ConfigError, match=r"does not record the view of its queries.*query_view=panorama \| sphere"):
        away.query_view
    assert away.input_spec("sphere")["query_view"] == "sphere"  # told, it needs no reader
    with pytest.raises(ValueError, match="query_view='drone' is not one of panorama, sphere, image"):
        away.input_spec("drone")


@pytest.mark.slow
@pytest.mark.parametrize("recorded", [True, False])
def test_university_1652_satellite_to_drone(tmp_path, recorded):
    """The query branch takes drone photos ("image"); the validation queries are aerial, as the reader says, for a
    new checkpoint (recorded) and an old one (asked)."""
    from geoloc.apps.export.onnx_export import queries_entry

    root = _u1652(tmp_path / "u1652")
    views = {"train": "image", "val": "aerial"} if recorded else None
    _checkpoint(tmp_path / "best.pt", ["dataset=u1652", f"dataset.root={root}", "dataset.alignment=none",
                                       "dataset.direction=satellite_to_drone"], views)
    encoder = CrossViewEncoder.load(tmp_path / "best.pt")
    assert encoder.query_views == {"train": "image", "val": "aerial"}
    shape, steps = encoder.input_spec()["query"]
    assert shape == (32, 32) and steps[-1] == "resize to 32x32 (cv2.INTER_AREA)"
    assert "1/8, 1/4, 1/2 scale whose sides stay >= 32x32" in steps[0]  # photos decode at reduced scale
    assert queries_entry(encoder, encoder.query_view)["queries"]["file"] == "reference.onnx"


@pytest.mark.parametrize("alignment, view, query_hw, reference_hw", [
    ("ipt", "panorama", (32, 32), (32, 32)),
    ("ipt", "sphere", (32, 32), (32, 32)),
    ("ground", "sphere", (32, 32), (32, 32)),
    ("polar", "panorama", (16, 64), (16, 64)),
    ("none", "panorama", (16, 64), (32, 32)),
    ("none", "image", (32, 32), (32, 32)),  # University-1652's drone photos: the aerial branch's square size
])
def test_input_shapes_follow_the_data_module(alignment, view, query_hw, reference_hw):
    """The spec's shapes are the shapes geoloc.tasks.crossview.transforms makes from real images of each view."""
    cfg = CrossViewDataConfig(alignment=alignment, aerial_size=32, pano_size=[16, 64])
    street = np.zeros((40 if view == "sphere" else 20, 120, 3), np.uint8)
    assert query_input(cfg, view)[0] == query_hw == align_query(street, cfg, view).shape[:2]
    assert reference_input(cfg)[0] == reference_hw == align_reference(np.zeros((50, 50, 3), np.uint8), cfg).shape[:2]


def test_one_rule_for_the_device(monkeypatch):
    assert resolve_device("cpu") == resolve_device("auto") == resolve_device(None) == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device(None) == torch.device("cuda") and resolve_device("cuda:1") == torch.device("cuda", 1)
    with pytest.raises(ValueError, match=r"device='cuda:2' but this machine has 2 CUDA device\(s\): use one of "
                                         "auto, cpu, cuda, cuda:0, cuda:1$"):
        resolve_device("cuda:2")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="device='cuda:1' but CUDA is not available on this machine: use one of "
                                         "auto, cpu$"):
        resolve_device("cuda:1")
    # not a name torch knows, and names torch knows that no geoloc code runs on: the valid names, not a traceback
    for name in ("gpu", "banana", "meta", "mps", "xpu", "cuda:x"):
        with pytest.raises(ValueError, match=f"device='{re.escape(name)}' is not a device: use one of auto, cpu$"):
            resolve_device(name)
