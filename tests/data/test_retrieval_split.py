"""RetrievalSplit's checks, and the metre distances between GPS positions."""
import numpy as np
import pytest
from geoloc.data.geo import (
    EARTH_RADIUS_M,
    centre_latlon,
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


def test_offsets_across_the_180_meridian_take_the_short_way_round():
    """Brute force: each offset's length is the haversine distance, across the meridian too; two places on the
    equator 0.0002° apart across it are 22.24 m apart, not nearly the Earth's circumference."""
    rng = np.random.default_rng(0)
    for origin in ((-16.5, 179.9999), (64.0, -179.9998), (0.0, 180.0), (10.0, 0.5)):
        east_north = rng.uniform(-300, 300, (20, 2))
        latlon = offset_to_latlon(origin, east_north[:, 0], east_north[:, 1])
        assert (np.abs(latlon[:, 1]) <= 180.0).all()
        np.testing.assert_allclose(haversine_m(origin, latlon), np.hypot(*east_north.T), rtol=1e-4)
        np.testing.assert_allclose(latlon_to_offset(origin, latlon), east_north, atol=1e-6)
        b = latlon[::-1]  # pairs of these points, either side of the meridian or not
        np.testing.assert_allclose(np.linalg.norm(latlon_to_offset(latlon[0], b), axis=1), haversine_m(latlon[0], b),
                                   rtol=2e-3)
    a, b = (0.0, 179.9999), (0.0, -179.9999)
    assert haversine_m(a, b) == pytest.approx(22.239, abs=1e-3)
    np.testing.assert_allclose(latlon_to_offset(a, [b]), [[22.239, 0.0]], atol=1e-3)
    np.testing.assert_allclose(latlon_to_offset(b, [a]), [[-22.239, 0.0]], atol=1e-3)
    np.testing.assert_allclose(centre_latlon([a, b]), [0.0, 180.0], atol=1e-9)  # not 0°: the meridian between them


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


def _tiles(**kw):
    """Three queries on two 64 x 32 tiles of 0.5 m per pixel; query 2 has one semi-positive."""
    args = dict(semi_positives=[[1], [0], [-1]], reference_size_px=[[64, 32], [64, 32]],
                reference_metres_per_px=[0.5, 0.5], query_tile_px=[[32, 16], [0, 32], [10, 4]],
                query_semi_tile_px=[[[1, 2]], [[3, 4]], [[5, 6]]])
    args.update(kw)
    return _split(**args)


def test_tile_geometry_and_query_positions():
    s = _tiles()
    assert s.reference_size_px.dtype == np.int64 and s.query_tile_px.dtype == np.float64
    np.testing.assert_array_equal(s.reference_extent_m, [[32, 16], [32, 16]])
    assert np.isnan(s.query_semi_tile_px[2]).all() and s.query_semi_tile_px[1].tolist() == [[3, 4]]  # -1: none
    # (east, north) metres from the positive's centre (row 32, col 16): the centre, the north-east corner, ...
    np.testing.assert_allclose(s.query_tile_offset_m(), [[0, 0], [8, 16], [-6, 11]])
    assert _tiles(reference_metres_per_px=None).query_tile_offset_m() is None
    assert _tiles(reference_metres_per_px=None).reference_extent_m is None
    unknown = _tiles(query_tile_px=[[32, 16], [np.nan, np.nan], [10, 4]])  # a query no tile shows
    assert np.isnan(unknown.query_tile_offset_m()[1]).all() and unknown.query_tile_offset_m()[2].tolist() == [-6, 11]


@pytest.mark.parametrize("kw, match", [
    (dict(reference_size_px=None), "reference_metres_per_px needs reference_size_px"),
    (dict(reference_size_px=None, reference_metres_per_px=None), "query_tile_px needs reference_size_px"),
    (dict(reference_size_px=[[64, 32]]), r"reference_size_px has shape \(1, 2\), expected \(2, 2\)"),
    (dict(reference_size_px=[[64, 32], [0, 32]]), r"reference_size_px row 1 = \[0, 32\] is not a \(height, width\)"),
    (dict(reference_metres_per_px=[0.5, -1.0]), r"reference_metres_per_px\[1\] = -1.0 \(r1\) is not a positive"),
    (dict(reference_metres_per_px=[0.5]), r"reference_metres_per_px has shape \(1,\), expected \(2,\)"),
    (dict(query_tile_px=[[32, 16], [0, 33], [10, 4]]), r"query_tile_px of query 1 \(q1\) is \[0.0, 33.0\], outside "
                                                        r"tile 1 \(r1\) of \[64, 32\] pixels"),
    (dict(query_tile_px=[[32, 16], [0, 32], [np.nan, 4]]), "query_tile_px of query 2"),
    (dict(query_tile_px=[[32, 16], [0, 32]]), r"query_tile_px has shape \(2, 2\), expected \(3, 2\)"),
    (dict(query_semi_tile_px=[[[1, 2]], [[3, np.inf]], [[5, 6]]]), "query_semi_tile_px of query 1 .* not a finite"),
    (dict(semi_positives=None), "query_semi_tile_px needs semi_positives"),
])
def test_bad_tile_geometry_is_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        _tiles(**kw)


def test_cutting_a_split_cuts_its_positions():
    from geoloc.tasks.crossview.datasets import limited

    s = limited(_tiles(), 2)
    assert s.num_queries == 2 and s.query_tile_px.shape == (2, 2) and s.query_semi_tile_px.shape == (2, 1, 2)
    assert s.reference_size_px.shape == (2, 2)  # not one-to-one: the gallery stays whole
    pairs = _split(queries=["q0", "q1"], positives=[0, 1], reference_size_px=[[8, 8]] * 2,
                   reference_metres_per_px=[1.0, 2.0], query_tile_px=[[4, 4]] * 2)
    one = limited(pairs, 1)
    assert one.num_references == 1 and one.reference_metres_per_px.tolist() == [1.0]
