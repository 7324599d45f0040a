"""A split name the dataset does not have (CVACT's `test` given to CVUSA) is a refusal listing the splits it has."""

from __future__ import annotations

import pytest
from geoloc.config import ConfigError
from geoloc.datasets.cvact import cvact_pairs
from geoloc.datasets.cvusa import cvusa, synthetic


def test_cvusa_lists_its_splits(tiny_cvusa):
    with pytest.raises(ConfigError, match=r"dataset.split='test' is not a split of CVUSA: split must be one of "
                                          r"\['train', 'val'\]"):
        cvusa(str(tiny_cvusa), "test")


def test_the_synthetic_data_refuses_before_rendering_a_world(tmp_path, monkeypatch):
    import geoloc.synthetic

    monkeypatch.setattr(geoloc.synthetic, "ensure_dataset", lambda *a, **k: pytest.fail("rendered"))
    with pytest.raises(ConfigError, match=r"split must be one of \['train', 'val'\]"):
        synthetic(str(tmp_path), "test")


def test_cvact_lists_its_splits(tmp_path):
    with pytest.raises(ConfigError, match=r"not a split of CVACT: split must be one of \['train', 'val', 'test'\]"):
        cvact_pairs(tmp_path, "testing")
