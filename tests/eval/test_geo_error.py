"""Top-1 references (the scorer's top-k) and their metre error (VIGOR's GPS in the file names): brute force, hand
metres, edges."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from geoloc.data.geo import haversine_m, offset_to_latlon
from geoloc.eval import scoring
from geoloc.eval.geo_error import metre_errors, metre_summary


def top1_indices(query, reference, chunk_size=None):
    return scoring.top_k(query, reference, 1, chunk_size=chunk_size)[1][:, 0]

CHICAGO = (41.8781, -87.6298)


def brute_top1(query, reference):
    """First index of each row's largest inner product, one pair at a time."""
    out = []
    for q in query:
        scores = [float(q @ r) for r in reference]
        out.append(max(range(len(scores)), key=lambda j: (scores[j], -j)))
    return out


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("chunk_size", [1, 7, None])
def test_top1_matches_brute_force(monkeypatch, dtype, chunk_size):
    g = torch.Generator().manual_seed(0)
    query = F.normalize(torch.randn(37, 8, generator=g, dtype=torch.float64), dim=1)
    reference = F.normalize(torch.randn(53, 8, generator=g, dtype=torch.float64), dim=1)
    want = brute_top1(query, reference)
    assert len(set(want)) > 10  # the answers spread over the gallery
    monkeypatch.setattr(scoring, "SCORE_BUDGET", 6 * (chunk_size or scoring.QUERY_CHUNK))  # 9 blocks of references
    got = top1_indices(query.to(dtype), reference.to(dtype), chunk_size=chunk_size)
    assert got.dtype == torch.int64 and got.tolist() == want


def test_top1_normalises_rows_like_recall():
    query = torch.tensor([[1.0, 0.1]])
    reference = torch.tensor([[10.0, 5.0], [1.0, 0.0]])  # the larger raw product, the smaller cosine
    assert top1_indices(query, reference).tolist() == [1]


@pytest.mark.parametrize("rows_per_block", [2, 100])
def test_a_tie_goes_to_the_lowest_index_in_any_block(monkeypatch, rows_per_block):
    reference = torch.tensor([[0.0, 1.0], [0.6, 0.8], [1.0, 0.0], [0.0, -1.0], [1.0, 0.0]], dtype=torch.float64)
    query = torch.tensor([[1.0, 0.0], [0.0, -1.0]], dtype=torch.float64)
    monkeypatch.setattr(scoring, "SCORE_BUDGET", rows_per_block * scoring.QUERY_CHUNK)  # 2: the tied rows apart
    assert top1_indices(query, reference).tolist() == [2, 3]


def test_hand_metres_from_offsets():
    reference = offset_to_latlon(CHICAGO, [0.0, 100.0, 0.0], [0.0, 0.0, -40.0])
    query = offset_to_latlon(CHICAGO, [10.0, 100.0, 3.0], [0.0, 25.0, -44.0])  # 10 m east, 25 m north, 5 m
    got = metre_errors(np.array([0, 1, 2]), query, reference)
    assert got == pytest.approx([10.0, 25.0, 5.0], abs=0.01)
    # the reference chosen matters: query 0 against reference 1 is 90 m away
    assert metre_errors([1], query[:1], reference) == pytest.approx([90.0], abs=0.01)


def test_metre_errors_match_a_loop():
    rng = np.random.default_rng(1)
    reference = offset_to_latlon(CHICAGO, rng.uniform(-500, 500, 20), rng.uniform(-500, 500, 20))
    query = offset_to_latlon(CHICAGO, rng.uniform(-500, 500, 9), rng.uniform(-500, 500, 9))
    top1 = torch.as_tensor(rng.integers(0, 20, 9))
    want = [float(haversine_m(query[i], reference[int(top1[i])])) for i in range(9)]
    assert metre_errors(top1, torch.as_tensor(query), reference).tolist() == want


def test_summary_thresholds_are_inclusive():
    errors = [0.0, 10.0, np.nextafter(10.0, 11.0), 25.0, 30.0, 50.0, np.nextafter(50.0, 51.0), 400.0]
    got = metre_summary(errors)
    assert got == {"median_m": (25.0 + 30.0) / 2, "within_10m": 2 / 8, "within_25m": 4 / 8, "within_50m": 6 / 8}
    assert all(type(v) is float for v in got.values())


def test_summary_median_of_an_odd_count():
    assert metre_summary(np.array([7.0, 1.0, 3.0]))["median_m"] == 3.0


@pytest.mark.parametrize("call,match", [
    (lambda: metre_errors([[0]], [[0.0, 0.0]], [[0.0, 0.0]]), r"top1 must be \(Q,\)"),
    (lambda: metre_errors([2], [[0.0, 0.0]], [[0.0, 0.0], [0.0, 1.0]]), r"top1 of query 0 is 2.*\[0, 2\)"),
    (lambda: metre_errors([0.0], [[0.0, 0.0]], [[0.0, 0.0]]), "top1 must hold integer"),
    (lambda: metre_errors([0, 0], [[0.0, 0.0]], [[0.0, 0.0]]), r"query_latlon must be \(2, 2\)"),
    (lambda: metre_errors([0], [[0.0, 0.0]], [0.0, 0.0]), r"reference_latlon must be \(N, 2\)"),
    (lambda: metre_errors([0], [[91.0, 0.0]], [[0.0, 0.0]]), r"query_latlon row 0 = \[91.0, 0.0\]"),
    (lambda: metre_errors([0], [[0.0, 0.0]], [[0.0, np.nan]]), "reference_latlon row 0"),
    (lambda: metre_summary([]), "non-empty 1-D"),
    (lambda: metre_summary([1.0, -2.0]), "entry 1 is -2.0"),
    (lambda: top1_indices(torch.ones(2, 3), torch.ones(4, 2)), "dimensions differ"),
    (lambda: top1_indices(torch.ones(2, 3), torch.ones(4, 3), chunk_size=-1), "chunk_size"),
])
def test_bad_input_names_the_argument(call, match):
    with pytest.raises((ValueError, TypeError), match=match):
        call()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_top1_on_the_gpu_matches_the_cpu():
    g = torch.Generator().manual_seed(2)
    query = F.normalize(torch.randn(300, 16, generator=g), dim=1)
    reference = F.normalize(torch.randn(2000, 16, generator=g), dim=1)
    got = top1_indices(query.cuda(), reference.cuda(), chunk_size=64)
    assert got.device.type == "cpu" and got.tolist() == top1_indices(query, reference).tolist()
