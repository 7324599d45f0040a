"""LocalizationResult.to_json(): the JSON localize.py prints and the service answers, key for key and in order; the
fields metric localisation will fill stay out of it until set."""
import json

import numpy as np
import pytest
from geoloc.tasks.crossview import LocalizationResult

TOPK = [{"rank": 1, "row": 4, "path": "bingmap/19/0000005.jpg", "x_m": 1.0, "y_m": 2.0, "score": 0.5,
         "heading_deg": 90.0}]


def test_the_json_is_todays_answer():
    result = LocalizationResult(image="pano.jpg", fov_deg=360.0, heading_deg=90.0, heading_source="search",
                                topk=TOPK, position={"x_m": 1.0, "y_m": 2.0}, positions="xy")
    assert json.dumps(result.to_json()) == (
        '{"image": "pano.jpg", "fov_deg": 360.0, "heading_deg": 90.0, "heading_source": "search", '
        '"position": {"x_m": 1.0, "y_m": 2.0}, "topk": ' + json.dumps(TOPK) + ', "positions": "xy"}')
    assert result.rows == [4] and result.scores == [0.5]
    result.truth, result.picture = {"row": 4, "rank": 1}, "out/pano.png"
    assert list(result.to_json())[-2:] == ["truth", "picture"]


def test_refinement_fields_appear_once_set_and_the_map_never():
    result = LocalizationResult(image=None, fov_deg=90.0, heading_deg=0.0, heading_source="given", topk=TOPK,
                                refined_position={"x_m": 1.5, "y_m": 2.5}, probability_map=np.ones((4, 4)) / 16,
                                confidence=0.8)
    answer = result.to_json()
    assert answer["refined_position"] == {"x_m": 1.5, "y_m": 2.5} and answer["confidence"] == 0.8
    assert "probability_map" not in answer and "truth" not in answer and answer["position"] is None


@pytest.mark.parametrize("kw, match", [(dict(heading_source="guessed"), "heading_source must be"),
                                       (dict(confidence=1.5), r"confidence must be a probability in \[0, 1\]")])
def test_bad_fields_are_refused(kw, match):
    args = dict(image=None, fov_deg=360.0, heading_deg=0.0, heading_source="search", topk=TOPK)
    with pytest.raises(ValueError, match=match):
        LocalizationResult(**{**args, **kw})
