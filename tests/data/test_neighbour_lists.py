"""Neighbour lists for the hard-batch samplers, checked against full-matrix brute force."""
import numpy as np
import pytest
import torch
from geoloc.data.geo import haversine_m
from geoloc.data.neighbours import descriptor_neighbour_lists, gps_neighbour_lists


def brute_gps(latlon, k, labels):
    full = haversine_m(latlon[:, None], latlon[None])
    out = np.full((len(latlon), k), -1)
    for i, row in enumerate(full):
        allowed = np.flatnonzero(labels != labels[i])
        nearest = allowed[np.argsort(row[allowed], kind="stable")][:k]
        out[i, :len(nearest)] = nearest
    return out


def brute_descriptors(query, reference, labels, k):
    places, first = np.unique(labels, return_index=True)
    scores = query @ reference[first].T
    out = []
    for i, row in enumerate(scores):
        order = [p for p in np.argsort(-row, kind="stable") if places[p] != labels[i]]
        out.append(first[order[:k]])
    return np.array(out)


@pytest.mark.parametrize("chunk_elements", [1_000, 10**7])  # 3 rows a block, and one block
def test_gps_lists_equal_brute_force(chunk_elements):
    rng = np.random.default_rng(0)
    latlon = np.stack([rng.uniform(41.8, 41.9, 300), rng.uniform(-87.7, -87.6, 300)], 1)
    labels = rng.integers(0, 120, 300)
    got = gps_neighbour_lists(latlon, 20, labels, chunk_elements=chunk_elements)
    assert got.dtype == np.int64 and got.shape == (300, 20)
    np.testing.assert_array_equal(got, brute_gps(latlon, 20, labels))
    assert (labels[got] != labels[:, None]).all()


def test_score_blocks_stay_within_the_chunk_budget(monkeypatch):
    from geoloc.data import neighbours

    sizes = []

    def spy(a, b):
        sizes.append(np.broadcast_shapes(np.shape(a)[:-1], np.shape(b)[:-1]))
        return haversine_m(a, b)

    monkeypatch.setattr(neighbours, "haversine_m", spy)
    gps_neighbour_lists(np.random.default_rng(0).uniform(0, 1, (250, 2)), 5, chunk_elements=1_000)
    assert max(rows * cols for rows, cols in sizes) <= 1_000 and sum(rows for rows, _ in sizes) == 250


def test_gps_lists_pad_rows_short_of_candidates_with_minus_one():
    rng = np.random.default_rng(1)
    latlon = rng.uniform(0, 0.01, (40, 2))
    labels = np.r_[np.zeros(35, np.int64), np.arange(1, 6)]  # a pair of place 0 has only 5 others to list
    got = gps_neighbour_lists(latlon, 8, labels, chunk_elements=100)
    np.testing.assert_array_equal(got, brute_gps(latlon, 8, labels))
    assert (got[:35, 5:] == -1).all() and (got[:35, :5] >= 35).all() and (got[35:] >= 0).all()


def test_gps_lists_default_to_one_place_per_pair_and_order_a_line():
    latlon = np.stack([np.zeros(10), np.arange(10) * 1e-4], 1)  # ~11 m apart along the equator
    got = gps_neighbour_lists(latlon, 2)
    assert got[0].tolist() == [1, 2] and got[9].tolist() == [8, 7]
    assert set(got[5].tolist()) == {4, 6}


@pytest.mark.parametrize("chunk_elements", [500, 10**7])
def test_descriptor_lists_equal_brute_force(chunk_elements):
    rng = np.random.default_rng(2)
    query = rng.normal(size=(300, 16)).astype(np.float32)
    reference = rng.normal(size=(300, 16)).astype(np.float32)
    labels = rng.integers(0, 150, 300)
    got = descriptor_neighbour_lists(query, reference, labels, 12, chunk_elements=chunk_elements)
    np.testing.assert_array_equal(got, brute_descriptors(query, reference, labels, 12))
    # torch tensors give the same lists
    same = descriptor_neighbour_lists(torch.from_numpy(query), torch.from_numpy(reference), labels, 12)
    np.testing.assert_array_equal(same, got)


def test_descriptor_lists_are_capped_at_the_other_places():
    rng = np.random.default_rng(3)
    query = rng.normal(size=(6, 4))
    labels = np.array([0, 0, 1, 1, 2, 2])
    got = descriptor_neighbour_lists(query, query, labels, 10)
    assert got.shape == (6, 2)  # two other places
    np.testing.assert_array_equal(got, brute_descriptors(query, query, labels, 10))
    assert set(got[0].tolist()) == {2, 4}  # a place is named by its first pair


def test_bad_inputs_name_the_problem():
    with pytest.raises(ValueError, match="NaN/inf"):
        descriptor_neighbour_lists(np.full((3, 2), np.nan), np.zeros((3, 2)), np.arange(3), 1)
    with pytest.raises(ValueError, match="same \\(N, D\\) shape"):
        descriptor_neighbour_lists(np.zeros((3, 2)), np.zeros((4, 2)), np.arange(3), 1)
    with pytest.raises(ValueError, match="labels must be \\(3,\\) integers"):
        descriptor_neighbour_lists(np.zeros((3, 2)), np.zeros((3, 2)), np.arange(4), 1)
    with pytest.raises(ValueError, match="\\(N, 2\\) array"):
        gps_neighbour_lists(np.zeros((3, 3)), 1)
    with pytest.raises(ValueError, match="1 positions are not finite"):
        gps_neighbour_lists(np.array([[0.0, 0.0], [np.nan, 1.0]]), 1)
    with pytest.raises(ValueError, match="integer >= 0"):
        gps_neighbour_lists(np.zeros((3, 2)), -1)
