import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from geoloc.data.dynamic import (CarlaFourPanelDataset, DataFormatError, DynamicDataset, EmptyCitiesDataset,
                                 load_class_fractions)
from geoloc.data.validate import DatasetFileError

REPO = Path(__file__).resolve().parents[1]
PALETTE = np.array([(0, 0, 0), (70, 70, 70), (190, 153, 153), (220, 220, 0), (157, 234, 50), (128, 64, 128),
                    (244, 35, 232), (107, 142, 35)], np.uint8)


def _scene(rng, size):
    """A static label map and a textured RGB rendering of it."""
    h, w = size
    lab = np.zeros((h, w), np.uint8)
    lab[h // 3 :, :] = 1  # buildings
    lab[h // 2 :, : w // 4] = 7  # vegetation
    lab[h // 2 : h // 2 + 2, w // 4 : w // 2] = 2  # fence
    lab[2 * h // 3 :, :] = 6  # sidewalk
    lab[3 * h // 4 :, :] = 5  # road
    lab[7 * h // 8, ::4] = 4  # road lines
    lab[h // 3 : h // 2, rng.integers(w // 2, w - 4) :] = 3  # others, place-specific
    rgb = PALETTE[lab].astype(np.int16)
    for _ in range(12):  # place-specific windows: corners for ORB
        y, x = rng.integers(h // 3, 2 * h // 3 - 4), rng.integers(0, w - 6)
        rgb[y : y + 4, x : x + 6] = rng.integers(0, 255, 3)
    return lab, np.clip(rgb + rng.integers(-8, 8, rgb.shape), 0, 255).astype(np.uint8)


def write_tiny_dynamic(root: Path, n_train: int = 4, n_val: int = 3, size=(64, 64), seed: int = 0) -> Path:
    """A `dynamic` layout folder (docs/dynamic_layout.md): one reference and one query per place."""
    rng = np.random.default_rng(seed)
    for d in ("splits", "rgb_dynamic", "rgb_static", "label_static", "label_dynamic", "mask_dynamic"):
        (root / d).mkdir(parents=True, exist_ok=True)
    (root / "geoloc_synthetic.json").write_text(json.dumps({"layout": "dynamic", "seed": seed}))
    header = "sample,place,role,x,y,yaw,sun_azimuth,sun_elevation\n"
    rows = {"train": [header], "val": [header]}
    counts = np.zeros(8)
    sample = 0
    for place in range(n_train + n_val):
        split = "train" if place < n_train else "val"
        lab, rgb = _scene(rng, size)
        for role in ("reference", "query"):
            shift = 0 if role == "reference" else int(rng.integers(-2, 3))
            lab_v, rgb_v = np.roll(lab, shift, axis=1), np.roll(rgb, shift, axis=1)
            dyn, mask = rgb_v.copy(), np.zeros(size, np.uint8)
            for _ in range(2):  # cars on the road
                y, x = rng.integers(3 * size[0] // 4 - 4, size[0] - 8), rng.integers(0, size[1] - 12)
                dyn[y : y + 8, x : x + 12] = (0, 0, 142)
                mask[y : y + 8, x : x + 12] = 255
            name = f"{sample:07d}"
            cv2.imwrite(str(root / f"rgb_static/{name}.png"), cv2.cvtColor(rgb_v, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(root / f"rgb_dynamic/{name}.png"), cv2.cvtColor(dyn, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(root / f"label_static/{name}.png"), lab_v)
            cv2.imwrite(str(root / f"label_dynamic/{name}.png"), np.where(mask > 0, 8, lab_v).astype(np.uint8))
            cv2.imwrite(str(root / f"mask_dynamic/{name}.png"), mask)
            rows[split].append(f"{name},{place},{role},0,0,0,0,45\n")
            if split == "train":
                counts += np.bincount(lab_v.ravel(), minlength=8)
            sample += 1
    for split, lines in rows.items():
        (root / f"splits/{split}.csv").write_text("".join(lines))
    (root / "class_fractions.json").write_text(json.dumps({"classes": [str(i) for i in range(8)],
                                                            "fractions": (counts / counts.sum()).tolist()}))
    return root


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


def write_four_panel(path: Path, h=16, w=24, seed=0, bad_tag=None):
    rng = np.random.default_rng(seed)
    dyn, sta = rng.integers(0, 255, (h, w, 3), np.uint8), rng.integers(0, 255, (h, w, 3), np.uint8)
    sta_tags = rng.integers(0, 13, (h, w)).astype(np.uint8)
    sta_tags[sta_tags == 4] = 7  # the static panel has no dynamic tags
    sta_tags[sta_tags == 10] = 8
    dyn_tags = sta_tags.copy()
    dyn_tags[:4, :4], dyn_tags[-3:, -5:] = 10, 4  # a vehicle and a pedestrian
    if bad_tag is not None:
        sta_tags[0, 0] = bad_tag
    rgb_tags = lambda t: np.repeat(t[..., None], 3, axis=2)
    img = np.concatenate([dyn, rgb_tags(dyn_tags), sta, rgb_tags(sta_tags)], axis=1)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    return dyn, sta, dyn_tags, sta_tags


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
