"""localize's confidence, abstention and heading prior on a real tiny checkpoint and gallery: the confidence is the
gallery calibrator's probability of the brute-force top-2 scores, given only for the condition it was fitted in;
abstain and heading_prior refuse bad values by name."""

from __future__ import annotations

import numpy as np
import pytest
from geoloc.apps.localize import Localizer, read_street
from geoloc.apps.query import QueryError, check_settings
from geoloc.datasets.cvusa import cvusa
from geoloc.tasks.crossview.datasets import CrossViewPairs
from geoloc.tasks.crossview.heading import query_inputs
from geoloc.tasks.crossview.transforms import normalise
from geoloc.gallery.confidence import NO_HOLDOUT
from geoloc.tasks.crossview.views import headings_around
from helpers.calibrated import KNOWN, calibrated_copy
from test_localize import brute_force, gallery  # noqa: F401  (gallery: a fixture)


@pytest.mark.parametrize("fields, problem", [
    ({"abstain": 1.5}, "abstain=1.5 is outside [0, 1]"), ({"abstain": "-0.1"}, "is outside [0, 1]"),
    ({"abstain": "nan"}, "abstain='nan' is not a finite number"), ({"abstain": "high"}, "is not a number"),
    ({"heading": 0, "heading_prior": 181}, "heading_prior=181 is outside [0, 180]"),
    ({"heading": 0, "heading_prior": -1}, "is outside [0, 180]"),
    ({"heading_prior": 10}, "heading_prior=10 is given without heading"),
    ({"heading": 0, "heading_prior": True}, "is not a number"),
])
def test_bad_abstain_thresholds_and_heading_priors_are_refused_by_name(fields, problem):
    with pytest.raises(QueryError, match=problem.replace("[", r"\[").replace("]", r"\]")) as err:
        check_settings(**fields)
    assert err.value.status == 422 and err.value.key in fields


def test_heading_prior_candidates_are_the_grid_steps_within_the_prior():
    assert headings_around(350.0, 25.0, 36).tolist() == [350.0, 340.0, 0.0, 330.0, 10.0]
    assert headings_around(30.0, 5.0, 36).tolist() == [30.0]  # under one step: the heading alone
    assert len(headings_around(0.0, 180.0, 36)) == 37  # ±180 reaches the opposite bearing from both sides
    assert check_settings(heading="10", heading_prior="0", abstain="0.25").abstain == 0.25


@pytest.fixture(scope="module")
def calibrated(gallery, tmp_path_factory):  # noqa: F811
    root, ckpt, folder = gallery
    copy = calibrated_copy(folder, tmp_path_factory.mktemp("calibrated") / "gallery")
    return root, Localizer.load(ckpt, copy, device="cpu", heading_steps=36), Localizer.load(ckpt, folder,
                                                                                             device="cpu")


def test_the_confidence_is_the_calibrator_on_the_top2_scores_for_a_given_heading(calibrated):
    root, loc, plain = calibrated
    pairs = CrossViewPairs(cvusa(str(root), "val"), loc.encoder.data, train=False)
    image = read_street(pairs.split.queries[2])
    answer = loc.localize(image, topk=1, heading=0)
    expect = brute_force(loc, normalise(pairs[2]["query"][None]), np.array([0.0]))  # uint8 item -> branch input
    top2 = [expect[0][1], expect[0][1] - expect[1][1]]
    assert answer.confidence == pytest.approx(float(KNOWN.probability([top2])[0]), abs=1e-5)
    assert answer.calibrated is True and answer.abstained is None and len(answer.topk) == 1
    assert loc.localize(image, heading=0, abstain=answer.confidence + 1e-3).abstained is True
    assert loc.localize(image, heading=0, abstain=answer.confidence - 1e-3).to_json()["abstained"] is False
    searched = loc.localize(image, heading="search").to_json()  # not the condition the confidence was fitted in
    assert "confidence" not in searched and searched["calibrated"] is False
    assert loc.info()["calibration"]["condition"] == {"heading": "given", "fov": 360.0}
    assert plain.localize(image, heading=0).calibrated is False
    assert plain.info()["calibration"] == {"calibrated": False, "why": NO_HOLDOUT}  # trained without a holdout


def test_abstain_needs_a_confidence_for_the_query(calibrated):
    root, loc, plain = calibrated
    image = read_street(cvusa(str(root), "val").queries[0])
    with pytest.raises(QueryError, match="abstain=0.5 needs the answer's confidence, and the gallery is "
                                         "uncalibrated: no labelled queries were kept out of training"):
        plain.localize(image, heading=0, abstain=0.5)
    with pytest.raises(QueryError, match=r"calibrated for \{'heading': 'given', 'fov': 360.0\}"):
        loc.localize(image, heading="search", abstain=0.5)
    with pytest.raises(QueryError, match="needs the answer's confidence"):
        loc.localize(image, heading=0, heading_prior=20, abstain=0.5)


def test_a_heading_prior_searches_only_the_candidates_around_the_heading(calibrated):
    root, loc, _ = calibrated
    image = read_street(cvusa(str(root), "val").queries[1])
    answer = loc.localize(image, topk=3, heading=100, heading_prior=20)
    headings = headings_around(100.0, 20.0, 36)
    inputs = query_inputs(image, loc.encoder.data, "panorama", 360.0, headings)
    expect = brute_force(loc, inputs, headings)[:3]
    assert [(h["row"], h["heading_deg"]) for h in answer.topk] == [(r, hd) for r, _, hd in expect]
    assert answer.heading_source == "prior" and 80.0 <= answer.heading_deg <= 120.0
    assert answer.confidence is None and answer.calibrated is False
