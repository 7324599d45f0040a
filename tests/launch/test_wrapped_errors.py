"""A corrupt split index or checkpoint gives an error naming the file and what to do, never a raw library error."""

from __future__ import annotations

import pytest
import torch
from geoloc.datasets.cvact import cvact_pairs
from geoloc.datasets.cvusa import cvusa_pairs
from geoloc.engine import checkpoint as ckpt_io
from helpers.cvact_data import write_act_mat

# ---- CVACT: ACT_data.mat ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("damage", ["garbage", "truncated", "empty", "html"])
def test_a_corrupt_act_data_mat_is_named(tmp_path, damage):
    write_act_mat(tmp_path, ["a", "b", "c"], train=[1, 2], val=[3])
    mat = tmp_path / "ACT_data.mat"
    data = mat.read_bytes()
    mat.write_bytes({"garbage": bytes(range(256)) * 4, "truncated": data[:len(data) // 2], "empty": b"",
                     "html": b"<html>Service unavailable</html>"}[damage])
    with pytest.raises(ValueError, match=rf"CVACT index {mat} is not a readable MATLAB file .* download ACT_data.mat"):
        cvact_pairs(tmp_path, "train")


def test_an_act_data_mat_of_another_structure_is_named(tmp_path):
    from scipy.io import savemat

    savemat(tmp_path / "ACT_data.mat", {"panoIds": ["a"], "trainSet": [[1.0]]})  # trainSet without trainInd
    with pytest.raises(ValueError, match=r"ACT_data.mat lacks panoIds or trainSet.trainInd"):
        cvact_pairs(tmp_path, "train")


# ---- CVUSA: the split csv ---------------------------------------------------------------------------------------
GOOD = "bingmap/19/0000001.jpg,streetview/panos/0000001.jpg,streetview/annotations/0000001.png\n"


@pytest.mark.parametrize("row,match", [
    ("bingmap/19/0000002.jpg\n", r"expected 'aerial,panorama,annotation' \(2 or 3 columns\), got 1"),
    ("a.jpg,b.jpg,c.png,d.png,e.png\n", r"expected .* \(2 or 3 columns\), got 5"),
    ("0000002,0000002,0000002\n", "'0000002' is not an image path relative to dataset.root"),
    ("/data/bingmap/19/0000002.jpg,streetview/panos/0000002.jpg,x.png\n", "'/data/bingmap/19/0000002.jpg' is not"),
    ("bingmap/19/0000002.jpg,../../etc/passwd.jpg,x.png\n", "'../../etc/passwd.jpg' is not an image path"),
])
def test_a_bad_split_row_is_named_with_its_line(tmp_path, row, match):
    (tmp_path / "splits").mkdir()
    csv = tmp_path / "splits" / "train-19zl.csv"
    csv.write_text(GOOD + row)
    with pytest.raises(ValueError, match=rf"{csv}:2: {match}"):
        cvusa_pairs(tmp_path, "train")


def test_a_binary_split_file_is_named(tmp_path):
    (tmp_path / "splits").mkdir()
    csv = tmp_path / "splits" / "train-19zl.csv"
    csv.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00garbage")
    with pytest.raises(ValueError, match=rf"CVUSA split file {csv} is not UTF-8 text"):
        cvusa_pairs(tmp_path, "train")


def test_a_byte_order_mark_is_not_part_of_the_first_path(tmp_path):
    (tmp_path / "splits").mkdir()
    (tmp_path / "splits" / "train-19zl.csv").write_bytes(b"\xef\xbb\xbf" + GOOD.encode())
    assert cvusa_pairs(tmp_path, "train") == [(tmp_path / "streetview/panos/0000001.jpg",
                                                tmp_path / "bingmap/19/0000001.jpg")]


# ---- checkpoints ------------------------------------------------------------------------------------------------
@pytest.fixture
def good_ckpt(tmp_path):
    path = tmp_path / "last.pt"
    ckpt_io.save_atomic({"task": {"w": torch.ones(64, 64)}, "config": "task: {name: crossview}\n", "epoch": 0}, path)
    return path


@pytest.mark.parametrize("damage,match", [
    ("empty", "it is empty \\(0 bytes\\)"),
    ("truncated", "it is truncated, corrupt or not a geoloc last.pt/best.pt"),
    ("text", "it is a Git LFS pointer, not the checkpoint itself: fetch it with `git lfs pull`"),
    ("pickle", "not a geoloc checkpoint: it holds objects a safe load refuses \\(WeightsUnpickler error: "
               "Unsupported global: GLOBAL print"),
    ("tensor", "it holds Tensor, not a geoloc checkpoint"),
    ("state_dict", r"it holds a dict with keys \['features.0.weight'\], not a geoloc checkpoint"),
])
def test_an_unreadable_checkpoint_is_named(good_ckpt, damage, match):
    data = good_ckpt.read_bytes()
    if damage == "empty":
        good_ckpt.write_bytes(b"")
    elif damage == "truncated":
        good_ckpt.write_bytes(data[:len(data) // 2])
    elif damage == "text":
        good_ckpt.write_text("version https://git-lfs.github.com/spec/v1\noid sha256:abc\nsize 123\n")
    elif damage == "pickle":  # a pickle that would run code: weights_only refuses it
        torch.save({"task": {}, "hook": print}, good_ckpt)
    elif damage == "tensor":
        torch.save(torch.ones(3), good_ckpt)
    else:  # another project's weights
        torch.save({"features.0.weight": torch.ones(3)}, good_ckpt)
    with pytest.raises(RuntimeError, match=rf"could not read checkpoint {good_ckpt}: .*{match}"):
        ckpt_io.load(good_ckpt)


def test_a_good_checkpoint_loads(good_ckpt):
    assert torch.equal(ckpt_io.load(good_ckpt)["task"]["w"], torch.ones(64, 64))
