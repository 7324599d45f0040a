"""RetrievalSplit's checks, and the metre distances between GPS positions."""
import numpy as np
import pytest
from geoloc.data.geo import (
    EARTH_RADIUS_M,
    haversine_m,
    latlon_to_offset,
    offset_to_latlon,
)
from geoloc.data.retrieval_split import RetrievalSplit


def _law_of_cosines_m(a, b):
    """VIGOR's gps2distance form, an independent formula (fine above a metre)."""
    la, lb = np.radians(a), np.radians(b)
    c = np.sin(la[0]) * np.sin(lb[0]) + np.cos(la[0]) * np.cos(lb[0]) * np.cos(la[1] - lb[1])
    return EARTH_RADIUS_M * np.arccos(np.clip(c, -1, 1))


def test_haversine_against_known_values_and_another_formula():
    assert haversine_m((0.0, 0.0), (1.0, 0.0)) == pytest.approx(EARTH_RADIUS_M * np.pi / 180, rel=1e-12)
    assert haversine_m((10.0, 20.0), (10.0, 20.0)) == 0.0
    rng = np.random.default_rng(0)
    a = np.column_stack([rng.uniform(-60, 60, 50), rng.uniform(-170, 170, 50)])
    b = a + rng.uniform(-0.05, 0.05, (50, 2))  # up to a few km apart
    brute = np.array([_law_of_cosines_m(p, q) for p, q in zip(a, b)])
    np.testing.assert_allclose(haversine_m(a, b), brute, rtol=1e-6)
    # broadcasting: one point against many
    assert haversine_m(a[0], b).shape == (50,)
    with pytest.raises(ValueError, match="lat, lon"):
        haversine_m([1.0, 2.0, 3.0], [1.0, 2.0])


def test_offsets_around_an_origin():
    origin = (41.8781, -87.6298)
    for east, north in ((100.0, 0.0), (0.0, -250.0), (-73.0, 36.5)):
        latlon = offset_to_latlon(origin, east, north)
        assert haversine_m(origin, latlon) == pytest.approx(np.hypot(east, north), abs=1e-3)
        np.testing.assert_allclose(latlon_to_offset(origin, latlon), [east, north], atol=1e-9)


def _split(**kw):
    args = dict(name="t", root="/r", queries=["q0", "q1", "q2"], references=["r0", "r1"], positives=[0, 1, 1])
    args.update(kw)
    return RetrievalSplit(**args)


def test_valid_split_is_normalised():
    s = _split(semi_positives=[[1, -1], [0, -1], [-1, -1]], query_latlon=[[1, 2], [3, 4], [5, 6]],
               query_labels=[7, 8, 8], reference_labels=[7, 8])
    assert s.positives.dtype == np.int64 and s.semi_positives.shape == (3, 2)
    assert s.num_queries == 3 and s.num_references == 2 and str(s.queries[0]) == "q0"
    assert s.reference_latlon is None


@pytest.mark.parametrize("kw, match", [
    (dict(queries=[]), "0 queries"),
    (dict(positives=[0, 1]), r"positives has shape \(2,\), expected \(3,\)"),
    (dict(positives=[0.0, 1.0, 1.0]), "must hold integers"),
    (dict(positives=[0, 2, 1]), r"positives must lie in \[0, 2\).*query 1 has 2"),
    (dict(semi_positives=[[1], [0], [-2]]), r"semi_positives must lie in \[-1, 2\).*query 2"),
    (dict(semi_positives=[1, 0, 1]), "semi_positives has shape"),
    (dict(query_latlon=[[1, 2], [3, 4]]), r"query_latlon has shape \(2, 2\), expected \(3, 2\)"),
    (dict(reference_latlon=[[1, 2], [95, 4]]), r"reference_latlon row 1 = \[95.0, 4.0\]"),
    (dict(query_labels=[1, 2, 3]), "together"),
    (dict(query_labels=[7, 8, 9], reference_labels=[7, 8]), "query 2 .* has label 9 but its positive reference 1"),
])
def test_bad_splits_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        _split(**kw)
