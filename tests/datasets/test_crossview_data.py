"""Split readers, alignment switch, start-up file validation, and the real samples (skipped when absent)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from geoloc.data.validate import DatasetFileError
from geoloc.datasets.cvact import cvact_pairs
from geoloc.datasets.cvusa import cvusa_pairs
from geoloc.tasks.crossview.data_config import CrossViewDataConfig

from geoloc.tasks.crossview.transforms import flip_rotate, load_view

from conftest import REALDATA
from helpers.crossview_runs import pairs_of
from helpers.cvact_data import write_act_mat  # noqa: F401


def cfg(root, **kw):
    base = dict(name="cvusa", root=str(root), aerial_size=32, pano_size=[16, 64], check_files="decode")
    return CrossViewDataConfig(**{**base, **kw})


def test_cvusa_split_rows_map_to_pano_and_aerial(tiny_cvusa):
    pairs = cvusa_pairs(tiny_cvusa, "val")
    assert len(pairs) == 8
    street, aerial = pairs[0]
    assert street == tiny_cvusa / "streetview/panos/0000013.jpg"
    assert aerial == tiny_cvusa / "bingmap/19/0000013.jpg"


@pytest.mark.parametrize("alignment,q_shape,r_shape", [
    ("ipt", (3, 32, 32), (3, 32, 32)), ("polar", (3, 16, 64), (3, 16, 64)), ("none", (3, 16, 64), (3, 32, 32))])
def test_alignment_switch_sets_the_shapes(tiny_cvusa, alignment, q_shape, r_shape):
    ds = pairs_of(cfg(tiny_cvusa, alignment=alignment), "train", train=True)
    item = ds[(3, 0)]
    assert item["query"].shape == q_shape and item["reference"].shape == r_shape and item["index"] == 3


def test_augmentation_is_a_function_of_seed_epoch_and_index(tiny_cvusa):
    ds = pairs_of(cfg(tiny_cvusa, rotation_deg=180, color_jitter=0.3), "train", train=True)
    assert torch.equal(ds[(2, 5)]["query"], ds[(2, 5)]["query"])
    assert not torch.equal(ds[(2, 5)]["query"], ds[(2, 6)]["query"])
    val = pairs_of(cfg(tiny_cvusa, rotation_deg=180, color_jitter=0.3), "val", train=False)
    assert torch.equal(val[(2, 5)]["query"], val[(2, 6)]["query"])  # no augmentation at validation


def test_missing_and_broken_files_are_counted_and_named(tiny_cvusa):
    (tiny_cvusa / "bingmap/19/0000014.jpg").unlink()
    (tiny_cvusa / "streetview/panos/0000015.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(DatasetFileError) as err:
        pairs_of(cfg(tiny_cvusa), "val", train=False)
    text = str(err.value)
    assert "2 of 16 files of split 'val'" in text and str(tiny_cvusa) in text
    assert "0000014.jpg (missing)" in text and "0000015.jpg (not an image: does not decode" in text


def test_missing_split_file_names_the_root(tmp_path):
    with pytest.raises(FileNotFoundError, match="train-19zl.csv"):
        cvusa_pairs(tmp_path, "train")


def test_cvact_indices_are_one_based(tmp_path):
    write_act_mat(tmp_path, ["a", "b", "c"], train=[1, 2], val=[3])
    pairs = cvact_pairs(tmp_path, "val")
    assert pairs == [(tmp_path / "ANU_data_small/streetview/c_grdView.jpg",
                      tmp_path / "ANU_data_small/satview_polish/c_satView_polish.jpg")]
    assert cvact_pairs(tmp_path, "test")[0][0].parent.parent.name == "ANU_data_test"
    write_act_mat(tmp_path, ["a"], train=[0], val=[1])
    with pytest.raises(ValueError, match="1-based"):
        cvact_pairs(tmp_path, "train")


@pytest.mark.skipif(not (REALDATA / "cvusa_mini").is_dir(), reason="../shared/realdata not present")
def test_real_cvusa_samples_load_and_transform():
    ds = pairs_of(CrossViewDataConfig(name="cvusa", root=str(REALDATA / "cvusa_mini"), aerial_size=288),
                         "val", train=False)
    assert len(ds) >= 1
    item = ds[0]
    assert item["query"].shape == item["reference"].shape == (3, 288, 288)
    assert torch.isfinite(item["query"]).all()


@pytest.mark.skipif(not (REALDATA / "cvact_mini").is_dir(), reason="../shared/realdata not present")
def test_real_cvact_sample_loads_with_a_written_act_data_mat(tmp_path):
    root = tmp_path / "cvact"
    root.mkdir()
    (root / "ANU_data_small").symlink_to(REALDATA / "cvact_mini" / "ANU_data_small")
    write_act_mat(root, ["sample01"], train=[1], val=[1])
    ds = pairs_of(CrossViewDataConfig(name="cvact", root=str(root), aerial_size=128), "val", train=False)
    street = load_view(ds.split.queries[0], ds.split.query_view)
    full = cv2.imread(str(REALDATA / "cvact_mini/ANU_data_small/streetview/sample01_grdView.jpg"))
    assert street.shape[0] == full.shape[0] // 2  # the horizon band rows 208:624 of 832
    assert ds[0]["query"].shape == (3, 128, 128)


@pytest.mark.parametrize("turns,flip", [(1, False), (2, False), (3, True), (0, True)])
def test_joint_flip_rotate_keeps_the_pair_geometrically_true(turns, flip):
    """aerial_to_polar(augmented aerial) must equal the augmented panorama built from aerial_to_polar(aerial)."""
    from geoloc.data.polar import aerial_to_polar

    rng = np.random.default_rng(0)
    aerial = cv2.resize(rng.integers(0, 255, (8, 8, 3), dtype=np.uint8), (128, 128), interpolation=cv2.INTER_CUBIC)
    street = aerial_to_polar(aerial, (32, 128))
    new_street, new_aerial = flip_rotate(street, aerial, turns, flip)
    expected = aerial_to_polar(new_aerial, (32, 128)).astype(int)
    error = np.abs(new_street.astype(int) - expected).mean()
    # a quarter turn the wrong way is far worse; the residual is the half-pixel shift of the image centre under
    # the flip/rotation (S/2 lies between pixels)
    wrong = np.abs(np.roll(new_street, 128 // 4, axis=1).astype(int) - expected).mean()
    assert error < 8 and error < 0.3 * wrong


def test_augment_seed_changes_the_augmentation(tiny_cvusa):
    c = cfg(tiny_cvusa, rotation_deg=180, color_jitter=0.3)
    seed0, seed1 = (pairs_of(c, "train", train=True, augment_seed=s) for s in (0, 1))
    assert not torch.equal(seed0[(2, 5)]["query"], seed1[(2, 5)]["query"])


@pytest.mark.slow
def test_the_runs_seed_reaches_init_sampling_and_augmentation(tiny_cvusa, tmp_path, monkeypatch):
    """`seed=7` (not dataset.seed, which picks the synthetic world) seeds what a seed sweep must vary."""
    from geoloc.tasks.crossview import crossview_run

    from conftest import TINY, compose_train

    seen = {}
    real_build = crossview_run.build

    def spy_build(data_cfg, reader, split, train, augment_seed=0, **options):
        seen[split] = augment_seed
        return real_build(data_cfg, reader, split, train, augment_seed, **options)

    def no_fit(trainer, task, *args, **kwargs):
        seen["trainer_seed"] = trainer.cfg.seed
        seen["first_weight"] = next(task.parameters()).detach().clone()
        return {}

    monkeypatch.setattr(crossview_run, "build", spy_build)
    monkeypatch.setattr(crossview_run.Trainer, "fit", no_fit)
    weights = []
    for seed in (7, 8):
        cfg_ = compose_train([*TINY, f"dataset.root={tiny_cvusa}", f"run_dir={tmp_path / str(seed)}", f"seed={seed}"])
        crossview_run.train(cfg_, tmp_path / str(seed))
        assert seen["train"] == seed and seen["trainer_seed"] == seed
        weights.append(seen["first_weight"])
    assert not torch.equal(*weights)  # initialisation follows the seed too
