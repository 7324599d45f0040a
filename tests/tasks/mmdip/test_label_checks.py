"""MMDIP checks its labels: ids outside the class set, stale class fractions, absent classes and single-class
labels are caught at start-up (a reader's class_fractions: geoloc.tasks.mmdip.datasets.class_fractions,
geoloc.data.label_census)."""

from __future__ import annotations

import json
import warnings

import cv2
import numpy as np
import pytest
from geoloc.data.validate import DatasetFileError
from geoloc.losses.segmentation import class_weights
from geoloc.tasks.mmdip import pipeline
from geoloc.tasks.mmdip.datasets import (
    CARLA_TO_STATIC,
    DataFormatError,
    DynamicDataset,
)
from geoloc.tasks.mmdip.readers import load_class_fractions

from conftest import compose_train
from helpers.dynamic_data import write_four_panel, write_tiny_dynamic

TRAIN_LABELS = [f"{i:07d}" for i in range(8)]  # write_tiny_dynamic: 4 train places x 2 views


def label_path(root, stem):
    return root / "label_static" / f"{stem}.png"


def brute_fractions(root, stems):
    counts = np.zeros(8)
    for s in stems:
        lab = cv2.imread(str(label_path(root, s)), cv2.IMREAD_UNCHANGED)
        counts += [(lab == c).sum() for c in range(8)]
    return counts / counts.sum()


def relabel(root, stems, old, new):
    for s in stems:
        lab = cv2.imread(str(label_path(root, s)), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(label_path(root, s)), np.where(lab == old, new, lab).astype(np.uint8))


@pytest.fixture
def root(tmp_path):
    return write_tiny_dynamic(tmp_path / "dyn")


def test_an_id_outside_the_class_set_fails_at_start_up_naming_the_file(root):
    lab = cv2.imread(str(label_path(root, "0000005")), cv2.IMREAD_UNCHANGED)
    lab[0, 0] = 11
    cv2.imwrite(str(label_path(root, "0000005")), lab)
    with pytest.raises(DataFormatError, match=r"label_static/0000005.png: label values \[11\] lie outside"):
        load_class_fractions(root)
    val = label_path(root, "0000009")  # a validation label: caught when the split is opened, not mid-training
    cv2.imwrite(str(val), np.full((64, 64), 200, np.uint8))
    with pytest.raises(DatasetFileError, match=r"0000009.png \(label values \[200\]"):
        DynamicDataset(root, "val")


def test_stored_fractions_follow_the_label_files(root):
    path = root / "class_fractions.json"
    first = load_class_fractions(root)  # the fixture's file records no source: counted again, with one
    np.testing.assert_allclose(first, brute_fractions(root, TRAIN_LABELS), atol=5e-7)
    record = json.loads(path.read_text())
    assert record["source"]["files"] == 8 and record["pixels"][1] > 0
    relabel(root, TRAIN_LABELS[:3], old=1, new=2)  # buildings become fences in three train maps
    second = load_class_fractions(root)
    np.testing.assert_allclose(second, brute_fractions(root, TRAIN_LABELS), atol=5e-7)
    assert second[2] > first[2] + 0.05  # the stale fractions were not used
    assert json.loads(path.read_text())["fractions"] == second  # and the stored file was brought up to date


def test_a_changed_split_makes_the_fractions_stale(root):
    load_class_fractions(root)
    csv = root / "splits" / "train.csv"
    lines = csv.read_text().splitlines(keepends=True)
    csv.write_text("".join(lines[:-2]))  # one place fewer
    fractions = load_class_fractions(root)
    assert json.loads((root / "class_fractions.json").read_text())["source"]["files"] == 6
    np.testing.assert_allclose(fractions, brute_fractions(root, TRAIN_LABELS[:6]), atol=5e-7)


def test_an_absent_class_is_reported_before_phase_1(root, tmp_path, monkeypatch):
    relabel(root, TRAIN_LABELS, old=2, new=1)  # no fence pixel left in the training split
    cfg = compose_train(["task=mmdip", f"dataset.root={root}", "trainer.device=cpu", f"run_dir={tmp_path}"])

    def phase1(*args, **kwargs):
        raise RuntimeError("phase 1 started")

    monkeypatch.setattr(pipeline, "run_phase1", phase1)
    with pytest.warns(UserWarning, match=r"classes \['Fences'\] have no pixel in the train labels"):
        with pytest.raises(RuntimeError, match="phase 1 started"):
            pipeline.train(cfg, tmp_path / "run")
        weights = class_weights(load_class_fractions(root))
    assert weights[2] == pytest.approx(1 / np.log(1.02), rel=1e-6)  # eq. 1 at r_c = 0: finite, the largest


def test_labels_of_a_single_class_fail_at_start_up(root):
    for s in TRAIN_LABELS:
        cv2.imwrite(str(label_path(root, s)), np.full((64, 64), 5, np.uint8))
    with pytest.raises(DataFormatError, match=r"every labelled pixel of the train split .* is class 5 \(Road\)"):
        load_class_fractions(root)


def test_carla_four_panel_fractions_record_the_class_map(tmp_path):
    folder = tmp_path / "carla" / "train"
    folder.mkdir(parents=True)
    tags = [write_four_panel(folder / f"{i}.png", seed=i)[3] for i in range(3)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every class is present: nothing to report
        fractions = load_class_fractions(tmp_path / "carla", "carla4")
    lut = np.array([CARLA_TO_STATIC[t] for t in range(13)])
    counts = np.bincount(np.concatenate([lut[t].ravel() for t in tags]), minlength=8)
    np.testing.assert_allclose(fractions, counts / counts.sum(), atol=5e-7)
    source = json.loads((tmp_path / "carla" / "class_fractions.json").read_text())["source"]
    assert source["format"] == "carla4" and source["class_map"]["10"] == 3
    write_four_panel(folder / "1.png", seed=1, bad_tag=20)
    with pytest.raises(DataFormatError, match=r"1.png: CARLA tags \[20\]"):
        load_class_fractions(tmp_path / "carla", "carla4")
