import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch
from geoloc.data.validate import DatasetFileError
from geoloc.tasks.mmdip.datasets import (
    CarlaFourPanelDataset,
    DataFormatError,
    DynamicDataset,
    EmptyCitiesDataset,
)
from geoloc.tasks.mmdip.readers import load_class_fractions

from conftest import REPO
from helpers.dynamic_data import (
    PALETTE,  # noqa: F401
    write_four_panel,
    write_tiny_dynamic,
)


def test_dynamic_layout_reader(tmp_path):
    root = write_tiny_dynamic(tmp_path / "dyn")
    ds = DynamicDataset(root, "train", check="decode")
    assert len(ds) == 8
    s = ds[(1, 0)]
    assert s["dynamic"].shape == s["static"].shape == (3, 64, 64)
    assert s["label"].shape == (64, 64) and s["label"].dtype == torch.int64 and s["label"].max() <= 7
    assert s["mask"].shape == (1, 64, 64) and set(s["mask"].unique().tolist()) <= {0.0, 1.0}
    assert s["is_query"].item() and s["place"].item() == 0
    assert len(DynamicDataset(root, "val", roles=("query",))) == 3
    resized = DynamicDataset(root, "train", image_size=(32, 48))[0]
    assert resized["static"].shape == (3, 32, 48) and resized["label"].shape == (32, 48)


def test_dynamic_augmentation_is_seeded_and_consistent(tmp_path):
    root = write_tiny_dynamic(tmp_path / "dyn")
    ds = DynamicDataset(root, "train", augment=True, seed=3)
    plain = DynamicDataset(root, "train")[0]
    flips = [torch.equal(ds[(0, e)]["static"], plain["static"].flip(-1)) for e in range(8)]
    assert any(flips) and not all(flips)
    for e in range(8):
        a, b = ds[(0, e)], ds[(0, e)]
        assert torch.equal(a["dynamic"], b["dynamic"])
        assert torch.equal(a["label"], plain["label"].flip(-1) if flips[e] else plain["label"])


def test_dynamic_reader_refuses_bad_files(tmp_path):
    root = write_tiny_dynamic(tmp_path / "dyn")
    cv2.imwrite(str(root / "label_static/0000002.png"), np.full((64, 64), 9, np.uint8))
    cv2.imwrite(str(root / "rgb_static/0000003.png"), np.zeros((64, 64), np.uint8))
    with pytest.raises(DatasetFileError, match=r"0000002.png \(label values \[9\] lie outside the class set 0..7"):
        DynamicDataset(root, "train")  # at start-up, not at the first validation
    ds = DynamicDataset(root, "train", check="off")
    with pytest.raises(DataFormatError, match=r"0000002.png: label values \[9\] lie outside"):
        ds[2]
    with pytest.raises(DataFormatError, match="0000003.png: expected a 3-channel RGB image, got 1"):
        ds[3]
    (root / "rgb_dynamic/0000004.png").unlink()
    with pytest.raises(Exception, match="0000004.png"):
        DynamicDataset(root, "train")
    (root / "geoloc_synthetic.json").write_text(json.dumps({"layout": "cvusa"}))
    with pytest.raises(DataFormatError, match="'cvusa' layout"):
        DynamicDataset(root, "train", check="off")


def test_carla_four_panel_reader_maps_tags(tmp_path):
    dyn, sta, dyn_tags, sta_tags = write_four_panel(tmp_path / "a.png")
    s = CarlaFourPanelDataset(tmp_path)[0]
    mapping = {0: 0, 1: 1, 2: 2, 3: 3, 4: 3, 5: 3, 10: 3, 11: 3, 12: 3, 6: 4, 7: 5, 8: 6, 9: 7}
    want = np.vectorize(mapping.get)(sta_tags)
    assert np.array_equal(s["label"].numpy(), want)
    assert np.array_equal(s["mask"][0].numpy() > 0, np.isin(dyn_tags, (4, 10)))
    assert torch.allclose(s["dynamic"], torch.from_numpy(dyn).permute(2, 0, 1) / 255.0)
    assert torch.allclose(s["static"], torch.from_numpy(sta).permute(2, 0, 1) / 255.0)
    assert CarlaFourPanelDataset(tmp_path, image_size=(32, 48))[0]["label"].shape == (32, 48)


def test_carla_four_panel_refuses_unknown_tags_and_bad_width(tmp_path):
    write_four_panel(tmp_path / "bad.png", bad_tag=13)
    with pytest.raises(DataFormatError, match=r"bad.png: CARLA tags \[13\]"):
        CarlaFourPanelDataset(tmp_path)[0]
    (tmp_path / "bad.png").unlink()
    cv2.imwrite(str(tmp_path / "odd.png"), np.zeros((8, 30, 3), np.uint8))
    with pytest.raises(DataFormatError, match="odd.png: width 30 does not split into 4"):
        CarlaFourPanelDataset(tmp_path)[0]


def test_empty_cities_three_panel_reader(tmp_path):
    rng = np.random.default_rng(0)
    h, w = 30, 40  # not 800x600: read, said, and resized to image_size
    dyn, sta = rng.integers(0, 255, (h, w, 3), np.uint8), rng.integers(0, 255, (h, w, 3), np.uint8)
    mask = np.zeros((h, w, 3), np.uint8)
    mask[5:10, 5:20] = 255
    cv2.imwrite(str(tmp_path / "x.png"), cv2.cvtColor(np.concatenate([dyn, sta, mask], 1), cv2.COLOR_RGB2BGR))
    s = EmptyCitiesDataset(tmp_path)[0]
    assert torch.allclose(s["static"], torch.from_numpy(sta).permute(2, 0, 1) / 255.0)
    assert s["mask"].sum() == 75 and "label" not in s
    assert EmptyCitiesDataset(tmp_path, image_size=(24, 32))[0]["dynamic"].shape == (3, 24, 32)
    cv2.imwrite(str(tmp_path / "y.png"), np.zeros((8, 31), np.uint8))
    with pytest.raises(DataFormatError, match="y.png: expected a 3-channel"):
        EmptyCitiesDataset(tmp_path)[1]


@pytest.mark.slow
def test_class_fractions_tool(tmp_path):
    root = write_tiny_dynamic(tmp_path / "dyn")
    path = root / "class_fractions.json"
    exact = json.loads(path.read_text())["fractions"]
    path.unlink()
    subprocess.run([sys.executable, str(REPO / "data_prep/class_fractions.py"), "--root", str(root)], check=True,
                   capture_output=True)
    stored = json.loads(path.read_text())
    np.testing.assert_allclose(stored["fractions"], exact, atol=5e-7)  # stored to 6 decimals
    assert stored["source"]["format"] == "dynamic" and stored["source"]["files"] == 8
    before = path.stat().st_mtime_ns
    assert load_class_fractions(root) == stored["fractions"]
    assert path.stat().st_mtime_ns == before  # up to date: read, not recounted
