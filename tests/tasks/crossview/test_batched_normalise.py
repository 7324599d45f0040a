"""Workers return uint8 images; the task normalises batches on the device. The batched path gives the per-image
numpy normalisation (and colour jitter) it replaces bit for bit, with the same random draws per (seed, epoch,
index)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from geoloc.datasets.cvusa import cvusa
from geoloc.engine.sampling import item_rng
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.datasets import CrossViewPairs
from geoloc.tasks.crossview.transforms import (IMAGENET_MEAN, IMAGENET_STD, align, flip_rotate, image_tensor,
                                               jitter_draw, load_view, normalise, normalised, to_tensor)
from geoloc.data.io import read_rgb
from torch.utils.data import default_collate


def numpy_to_tensor(img: np.ndarray, rng: np.random.Generator | None = None, jitter: float = 0.0) -> torch.Tensor:
    """The per-image encoding the data workers ran before: float32 numpy, jitter in numpy's promoted float64."""
    x = img.astype(np.float32) / 255.0
    if rng is not None and jitter > 0:
        b, c, s = rng.uniform(1 - jitter, 1 + jitter, size=3)
        x = x * b
        mean = x.mean()
        x = (x - mean) * c + mean
        gray = x.mean(axis=2, keepdims=True)
        x = np.clip((x - gray) * s + gray, 0.0, 1.0)
    x = (x - IMAGENET_MEAN) / IMAGENET_STD
    return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1), dtype=np.float32))


@pytest.mark.parametrize("jitter", [0.0, 0.1, 0.4])
def test_a_batch_is_normalised_as_each_image_was(jitter):
    g = np.random.default_rng(7)
    images = [g.integers(0, 256, (37, 53, 3), dtype=np.uint8) for _ in range(5)]
    images[0][:5] = 0  # clipped and saturated pixels too
    images[1][:5] = 255
    expected = torch.stack([numpy_to_tensor(img, np.random.default_rng(i), jitter) for i, img in enumerate(images)])
    draws = None
    if jitter:
        draws = torch.stack([torch.from_numpy(jitter_draw(img, np.random.default_rng(i), jitter))
                             for i, img in enumerate(images)])
    got = normalise(torch.stack([image_tensor(img) for img in images]), draws)
    assert got.dtype == torch.float32 and torch.equal(got, expected)
    assert torch.equal(to_tensor(images[2]), numpy_to_tensor(images[2]))  # the apps' one-image path


def tiny_cfg(root, **kw) -> CrossViewDataConfig:
    """Full-size decoding, as the default run's data (reduced decoding is tested in test_reduced_decode.py)."""
    return CrossViewDataConfig(**{**dict(name="cvusa", root=str(root), aerial_size=32, pano_size=[16, 64],
                                         reduced_decode=False), **kw})


@pytest.mark.parametrize("kw", [dict(), dict(color_jitter=0.3, rotation_deg=20.0, joint_flip_rotate=True),
                                dict(alignment="polar", color_jitter=0.1), dict(alignment="none", fov=120.0,
                                                                                 random_heading=True)])
def test_training_items_reach_the_network_exactly_as_before(tiny_cvusa, kw):
    """Items of the training pairs, collated and normalised, equal the old worker's per-item tensors, augmentation
    draws included (align's, then the query's jitter, then the reference's, from the item's generator)."""
    cfg = tiny_cfg(tiny_cvusa, **kw)
    split = cvusa(str(tiny_cvusa), "train")
    pairs = CrossViewPairs(split, cfg, train=True, augment_seed=3)
    keys = [(0, 0), (5, 2), (11, 7)]
    items = [pairs[key] for key in keys]
    assert items[0]["query"].dtype == items[0]["reference"].dtype == torch.uint8
    batch = normalised(default_collate(items))
    assert not any(k.endswith("_jitter") for k in batch)  # the draws are used up
    for row, (index, epoch) in enumerate(keys):
        rng = item_rng(3, (index, epoch))
        street, aerial = load_view(split.queries[index], "panorama"), read_rgb(split.references[index])
        query, reference = align(street, aerial, cfg, rng, "panorama")
        expected_query = numpy_to_tensor(query, rng, cfg.color_jitter)
        expected_reference = numpy_to_tensor(reference, rng, cfg.color_jitter)
        assert torch.equal(batch["query"][row], expected_query)
        assert torch.equal(batch["reference"][row], expected_reference)


def test_images_are_normalised_exactly_once():
    image = torch.randint(0, 256, (2, 3, 4, 5), dtype=torch.uint8)
    once = normalised({"image": image, "index": torch.arange(2)})
    assert torch.equal(normalised(once)["image"], once["image"])  # float images pass through
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, H, W\) uint8"):
        normalise(once["image"])
    candidates = torch.randint(0, 256, (2, 4, 3, 4, 5), dtype=torch.uint8)  # B×K candidate headings
    assert torch.equal(normalise(candidates)[1, 2], normalise(candidates[1, 2]))


def turned_one_by_one(street: np.ndarray, aerial: np.ndarray, quarter_turns: int, flip: bool):
    """The joint flip / rotation as a column gather and one quarter turn at a time (what flip_rotate computes)."""
    w = street.shape[1]
    if flip:
        aerial = aerial[:, ::-1]
        street = street[:, (-np.arange(w)) % w]
    for _ in range(quarter_turns):
        aerial = cv2.rotate(np.ascontiguousarray(aerial), cv2.ROTATE_90_CLOCKWISE)
        street = np.roll(street, w // 4, axis=1)
    return street, aerial


@pytest.mark.parametrize("quarter_turns", [0, 1, 2, 3])
@pytest.mark.parametrize("flip", [False, True])
def test_the_joint_flip_rotation_moves_every_pixel_as_the_one_turn_at_a_time_version(quarter_turns, flip):
    g = np.random.default_rng(quarter_turns)
    street, aerial = g.integers(0, 256, (5, 70, 3), dtype=np.uint8), g.integers(0, 256, (9, 12, 3), dtype=np.uint8)
    got, expected = flip_rotate(street, aerial, quarter_turns, flip), turned_one_by_one(street, aerial,
                                                                                         quarter_turns, flip)
    assert np.array_equal(got[0], expected[0]) and np.array_equal(got[1], expected[1])
    assert got[0].flags.c_contiguous and got[1].flags.c_contiguous
