"""The refiner over the whole tile: which query-tile pairs hold the truth, the whole-tile summary against brute force,
the ground scale as an input, and the old checkpoints' window normalisation kept."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.fine_error import whole_tile_summary
from geoloc.tasks.crossview.legacy import upgraded_refiner
from geoloc.tasks.crossview.refine import RefineConfig
from geoloc.tasks.crossview.refine_items import tile_pairs, truth_fraction
from omegaconf import OmegaConf


def two_query_split():
    """Two queries in 64 px tiles: query 0 with its positive and three semi-positives, the last of them outside
    its tile (a corrected VIGOR label); query 1 with one semi-positive."""
    semi = np.array([[1, 2, 3], [0, -1, -1]])
    semi_px = np.array([[[10.0, 60.0], [63.0, 2.0], [-1.0, 30.0]], [[5.0, 5.0], [np.nan] * 2, [np.nan] * 2]])
    return RetrievalSplit("two", "/d", ["q0", "q1"], [f"t{i}" for i in range(4)], positives=[0, 2],
                          semi_positives=semi, reference_size_px=np.full((4, 2), 64),
                          reference_metres_per_px=np.full(4, 0.5), query_tile_px=[[30.0, 33.0], [20.0, 40.0]],
                          query_semi_tile_px=semi_px)


def test_tile_pairs_are_the_positive_and_the_semi_positives_that_hold_the_truth():
    split = two_query_split()
    assert [a.tolist() for a in tile_pairs(split, False)] == [[0, 1], [0, 2]]
    queries, tiles = tile_pairs(split, True)
    assert queries.tolist() == [0, 0, 0, 1, 1] and tiles.tolist() == [0, 1, 2, 2, 0]
    assert [a.tolist() for a in tile_pairs(split, True, [1])] == [[1, 1], [2, 0]]
    assert truth_fraction(split, 0, 2).tolist() == [63 / 64, 2 / 64]


def test_the_whole_tile_summary_is_its_brute_force():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 1, (400, 2))
    errors = rng.gamma(2.0, 2.0, 400)
    out = whole_tile_summary(errors, truth)
    edge = [e for e, (r, c) in zip(errors, truth) if min(r, c) < 0.1 or max(r, c) > 0.9]
    centre = [e for e, (r, c) in zip(errors, truth) if 0.25 <= r <= 0.75 and 0.25 <= c <= 0.75]
    assert out["whole_tile_edge_median_m"] == pytest.approx(np.median(edge))
    assert out["whole_tile_centre_median_m"] == pytest.approx(np.median(centre))
    assert out["whole_tile_median_m"] == pytest.approx(np.median(errors))
    assert out["whole_tile_within_3m"] == pytest.approx(np.mean(errors <= 3))
    nowhere = whole_tile_summary([1.0, 2.0], [[0.5, 0.5], [0.4, 0.6]])
    assert np.isnan(nowhere["whole_tile_edge_median_m"]) and nowhere["whole_tile_centre_median_m"] == 1.5


def test_the_ground_scale_is_an_input_only_where_asked():
    assert RefineConfig().query_scale([[64.52, 64.52]]) is None
    scale = RefineConfig(query_extent_m=72.96).query_scale([[64.52, 64.52], [75.61, 75.61]])
    assert scale.tolist() == pytest.approx([72.96 / 64.52, 72.96 / 75.61])
    with pytest.raises(ValueError, match="no metres per pixel"):
        RefineConfig(query_extent_m=72.96).query_scale([[np.nan, np.nan]])
    with pytest.raises(ValueError, match="query_extent_m must be a number of metres >= 0"):
        RefineConfig(query_extent_m=-1.0)


def test_a_stored_correlation_refiner_keeps_its_window_normalisation_and_loads_without_scale_jitter():
    old = OmegaConf.create({"refiner": {"name": "correlation", "width": 32}, "model": {"dim": 8}})
    assert upgraded_refiner(old).refiner.overlap == "window"
    new = OmegaConf.create({"refiner": {"name": "correlation", "overlap": "mean"}})
    assert upgraded_refiner(new).refiner.overlap == "mean"
    plug_in = OmegaConf.create({"refiner": {"name": "dot_map"}})
    assert "overlap" not in upgraded_refiner(plug_in).refiner
    assert upgraded_refiner(OmegaConf.create({"model": {"dim": 8}})) == OmegaConf.create({"model": {"dim": 8}})
    jittered = OmegaConf.create({"refiner": {"name": "correlation", "overlap": "mean", "scale_jitter": 0.1}})
    assert OmegaConf.to_container(upgraded_refiner(jittered).refiner) == {"name": "correlation", "overlap": "mean"}


def test_query_scale_reaches_the_refiner_through_match():
    from geoloc.tasks.crossview.refine import match

    seen = {}

    class Spy(torch.nn.Module):
        def match(self, query, reference, headings, **kwargs):
            seen.update(kwargs)

    match(Spy(), RefineConfig(), torch.zeros(2, 1), torch.zeros(2, 1), torch.zeros(1), [[64.0, 64.0]] * 2)
    assert seen == {}  # a refiner without the scale input is called as before
    match(Spy(), RefineConfig(query_extent_m=72.0), torch.zeros(2, 1), torch.zeros(2, 1), torch.zeros(1),
          [[64.0, 64.0], [72.0, 72.0]])
    assert seen["query_scale"].tolist() == pytest.approx([72.0 / 64.0, 1.0])


def spike_beside_bump(rows: int = 33) -> torch.Tensor:
    """1 x 1 x rows x rows log-probabilities: 0.8 in a broad bump at lattice (20, 9), 0.2 on the one point (6, 26)."""
    ys, xs = np.meshgrid(np.arange(rows), np.arange(rows), indexing="ij")
    bump = np.exp(-((ys - 20.0) ** 2 + (xs - 9.0) ** 2) / (2 * 3.0 ** 2))
    prob = 0.8 * bump / bump.sum()
    prob[6, 26] += 0.2
    return torch.from_numpy(np.log(prob)).float()[None, None]


def test_the_evaluation_and_the_calibration_read_the_answer_with_the_configured_peak_smoothing():
    from geoloc.models.refiners import Refinement
    from geoloc.tasks.crossview.refine import refined
    from geoloc.tasks.crossview.refine_confidence import refiner_condition

    class Fixed(torch.nn.Module):
        def match(self, query, reference, headings):
            return Refinement(spike_beside_bump().expand(len(query), 1, 33, 33), torch.zeros(1))

    split = two_query_split()
    raw, _, raw_mass = refined(Fixed(), RefineConfig(), torch.zeros(2, 1), torch.zeros(4, 1), [0, 1], [0, 2],
                               torch.zeros(1), split)
    smoothed, _, mass = refined(Fixed(), RefineConfig(peak_smoothing=0.0625), torch.zeros(2, 1), torch.zeros(4, 1),
                                [0, 1], [0, 2], torch.zeros(1), split)
    assert np.allclose(raw.numpy() * 32, [[6, 26]] * 2, atol=0.1)
    assert np.allclose(smoothed.numpy() * 32, [[20, 9]] * 2, atol=0.1)
    assert (mass > raw_mass).all()  # the mass within 5 m is counted around the answer given
    with pytest.raises(ValueError, match="peak_smoothing must be a share of the tile's side"):
        RefineConfig(peak_smoothing=-0.1)
    plain = refiner_condition(Fixed(), RefineConfig())
    assert "peak_smoothing" not in plain  # galleries calibrated before the key stay valid for such refiners
    assert refiner_condition(Fixed(), RefineConfig(peak_smoothing=0.05))["peak_smoothing"] == 0.05


def test_edge_weight_weighs_the_truths_near_the_edge_in_the_loss():
    nll = torch.tensor([1.0, 2.0, 4.0, 8.0])
    truth = torch.tensor([[0.5, 0.5], [0.05, 0.5], [0.5, 0.95], [0.3, 0.3]])  # the 2nd and 3rd are edge truths
    assert RefineConfig().loss(nll, truth) == nll.mean()
    expected = (1.0 + 3 * 2.0 + 3 * 4.0 + 8.0) / (1 + 3 + 3 + 1)  # the weighted mean, by hand
    assert RefineConfig(edge_weight=3.0).loss(nll, truth).item() == pytest.approx(expected)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="refiner.edge_weight must be a weight > 0"):
            RefineConfig(edge_weight=bad)
