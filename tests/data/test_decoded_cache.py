"""dataset.cache_decoded: each training image decoded once, and the items (augmentation included) unchanged."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from geoloc.data.decoded import DecodedImages
from geoloc.tasks.crossview import datasets as crossview_data
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.datasets import CrossViewPairs, read_split

from conftest import write_cvusa


def test_an_image_is_decoded_once_and_kept_read_only():
    calls = []

    def decode():
        calls.append(1)
        return np.zeros((4, 4, 3), np.uint8)

    kept = DecodedImages(enabled=True)
    first, again = kept.get("a.jpg", decode), kept.get("a.jpg", decode)
    assert first is again and len(calls) == 1 and kept.nbytes == 48
    with pytest.raises(ValueError, match="read-only"):
        first[0, 0, 0] = 1  # an in-place edit downstream would change every later epoch: it fails instead
    off = DecodedImages(enabled=False)
    off.get("a.jpg", decode), off.get("a.jpg", decode)
    assert len(calls) == 3 and off.nbytes == 0


def augmented(root, cache: bool) -> CrossViewDataConfig:
    # every train-time augmentation of a panorama dataset that works on the decoded arrays
    return CrossViewDataConfig(name="cvusa", root=str(root), aerial_size=32, pano_size=[16, 64], cache_decoded=cache,
                               joint_flip_rotate=True, rotation_deg=20, color_jitter=0.2)


def count_reads(monkeypatch) -> list:
    """The paths the training pairs decode from now on (every street and aerial read goes through load_view)."""
    reads, real = [], crossview_data.load_view

    def spy(path, view, size):
        reads.append(path)
        return real(path, view, size)

    monkeypatch.setattr(crossview_data, "load_view", spy)
    return reads


def test_cached_items_equal_decoded_ones_over_epochs(tmp_path, monkeypatch):
    root = write_cvusa(tmp_path / "cvusa", n_train=4, n_val=1)
    reads = count_reads(monkeypatch)
    split = read_split(augmented(root, False), {"name": "cvusa"}, "train")
    plain = CrossViewPairs(split, augmented(root, False), train=True, augment_seed=3)
    cached = CrossViewPairs(split, augmented(root, True), train=True, augment_seed=3)
    keys = [(i, epoch) for epoch in range(3) for i in range(4)]
    for key in keys:
        a, b = plain[key], cached[key]
        assert a.keys() == b.keys()
        for name in a:
            if isinstance(a[name], torch.Tensor):
                assert torch.equal(a[name], b[name]), (key, name)
            else:
                assert np.array_equal(a[name], b[name]), (key, name)
    assert len(reads) == 2 * len(keys) + 2 * 4  # plain: two files per item; cached: each of the 8 files once
    assert cached.decoded.nbytes > 0


def test_evaluation_items_are_never_kept(tmp_path):
    root = write_cvusa(tmp_path / "cvusa", n_train=2, n_val=1)
    split = read_split(augmented(root, True), {"name": "cvusa"}, "train")
    pairs = CrossViewPairs(split, augmented(root, True), train=False)
    pairs[0]
    assert pairs.decoded.nbytes == 0  # the cache is a training option: a gallery is read once anyway
