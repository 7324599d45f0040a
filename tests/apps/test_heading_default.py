"""A query that gives no heading follows the checkpoint: searched only when it was trained with an unknown heading,
else north (0), as trained; `heading=search` asks for the search whatever the checkpoint."""

from __future__ import annotations

from dataclasses import replace

import pytest
from geoloc.apps.localize import Localizer, read_street
from geoloc.apps.query import QueryError, check_settings
from geoloc.datasets.cvusa import cvusa
from test_localize import gallery  # noqa: F401  (a fixture: a 1-epoch north-aligned TINY checkpoint and its gallery)


@pytest.fixture(scope="module")
def loaded(gallery):  # noqa: F811
    root, ckpt, folder = gallery
    return Localizer.load(ckpt, folder, device="cpu", heading_steps=4), read_street(cvusa(str(root), "val").queries[0])


def test_a_north_aligned_checkpoint_answers_at_north_unless_a_search_is_asked(loaded):
    loc, image = loaded
    assert loc.info()["default_heading"] == 0.0
    default = loc.localize(image, topk=3)
    assert (default.heading_source, default.heading_deg) == ("given", 0.0)
    assert default.topk == loc.localize(image, topk=3, heading=0).topk
    assert loc.localize(image, topk=3, heading="search").heading_source == "search"
    assert loc.localize(image, topk=3, heading=" Search ").heading_source == "search"


def test_a_checkpoint_trained_with_an_unknown_heading_searches_by_default(loaded, monkeypatch):
    loc, image = loaded
    monkeypatch.setattr(loc.encoder, "data", replace(loc.encoder.data, random_heading=True))
    assert loc.info()["default_heading"] == "search"
    assert loc.localize(image, topk=3).heading_source == "search"
    assert loc.localize(image, topk=3, heading=90).heading_source == "given"


@pytest.mark.parametrize("fields,problem", [({"heading": "north"}, "heading='north' is not a number"),
                                            ({"heading": "search", "heading_prior": 20}, "given without heading")])
def test_search_is_the_one_word_a_heading_takes(fields, problem):
    with pytest.raises(QueryError, match=problem):
        check_settings(**fields)
