"""The refiner's truth and metric conventions: a tile fraction follows the joint flip / rotation of its tile, VIGOR's
offsets round-trip offset -> pixel -> metres -> lat/lon, the fixed test headings, the heading candidates, and the
fine / end-to-end summaries against brute force."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from geoloc.data.geo import haversine_m
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.fine_error import e2e_summary, fine_summary, heading_summary
from geoloc.eval.scoring import top_k
from geoloc.tasks.crossview.refine import RefineConfig, e2e_errors_m, fraction_error_m, offset_m, refined_positions
from geoloc.tasks.crossview.refine_items import eval_offset, truth_fraction, turned_fraction
from geoloc.tasks.crossview.transforms import flip_rotate


@pytest.mark.parametrize("turns", [0, 1, 2, 3])
@pytest.mark.parametrize("flip", [False, True])
def test_a_tile_fraction_follows_flip_rotate(turns, flip):
    """A marked pixel of the tile, turned as training turns it, is where turned_fraction says."""
    aerial = np.zeros((40, 40, 3), np.uint8)
    aerial[9, 30] = 255  # pixel (9, 30): its centre is the fraction (9.5 / 40, 30.5 / 40)
    street = np.zeros((8, 16, 3), np.uint8)
    _, turned = flip_rotate(street, aerial, turns, flip)
    row, col = np.argwhere(turned[..., 0] == 255)[0]
    got = turned_fraction(np.array([9.5 / 40, 30.5 / 40]), turns, flip)
    assert got == pytest.approx([(row + 0.5) / 40, (col + 0.5) / 40])


def vigor_like(offsets_px, scale=0.111262):
    """A one-tile VIGOR split: the tile at (41.87, -87.68), 640 px; queries at VIGOR offsets (north, east) px, placed
    at their true lat/lon (the tile centre minus the offset, in metres)."""
    centre = np.array([41.87, -87.68])
    offsets = np.asarray(offsets_px, np.float64)
    px = np.column_stack([320 + offsets[:, 0], 320 - offsets[:, 1]])  # docs/conventions.md "VIGOR split lines"
    from geoloc.data.geo import offset_to_latlon

    latlon = np.stack([offset_to_latlon(centre, -e * scale, -n * scale) for n, e in offsets])
    q = len(offsets)
    return RetrievalSplit("v", "/r", [f"q{i}" for i in range(q)], ["t0"], positives=np.zeros(q, int),
                          query_latlon=latlon, reference_latlon=centre[None], reference_size_px=[[640, 640]],
                          reference_metres_per_px=[scale], query_tile_px=px)


def test_offsets_round_trip_through_pixels_metres_and_latlon():
    split = vigor_like([[23.0, -29.0], [-100.5, 40.25], [0.0, 0.0]])
    truth = np.stack([truth_fraction(split, i, 0) for i in range(3)])
    assert truth[0] * 640 == pytest.approx([343.0, 349.0])
    # east / north metres of the fraction from the tile centre: minus the offset times the scale
    assert offset_m(truth, split.reference_extent_m[[0, 0, 0]]) == pytest.approx(
        -np.array([[-29.0, 23.0], [40.25, -100.5], [0.0, 0.0]]) * 0.111262)
    kind, found = refined_positions(truth, np.zeros(3, int), split)
    assert kind == "latlon" and haversine_m(found, split.query_latlon).max() < 0.01
    assert e2e_errors_m(truth, np.zeros(3, int), split).max() < 0.01
    # a fraction one pixel east of the truth is one pixel's metres off
    east = truth + np.array([0.0, 1 / 640])
    assert fraction_error_m(east, truth, split, [0, 0, 0]) == pytest.approx([0.111262] * 3)
    assert e2e_errors_m(east, np.zeros(3, int), split) == pytest.approx([0.111262] * 3, abs=1e-3)


def test_the_test_headings_are_fixed_and_within_the_prior():
    draws = [eval_offset(i, 30.0) for i in range(200)]
    assert draws == [eval_offset(i, 30.0) for i in range(200)]
    assert max(abs(d) for d in draws) <= 30.0 and np.std(draws) > 10.0
    assert eval_offset(7, 0.0) == 0.0


def test_heading_candidates():
    assert RefineConfig().candidates(36).tolist() == [0.0]
    assert len(RefineConfig(orientation_noise_deg=180).candidates(36)) == 36
    prior = RefineConfig(orientation_noise_deg=20).candidates(36).tolist()
    assert sorted(prior) == [0.0, 10.0, 20.0, 340.0, 350.0]
    with pytest.raises(ValueError, match="stage"):
        RefineConfig(stage="both")


def test_summaries_against_brute_force():
    e = np.array([0.5, 1.0, 2.9, 3.0, 7.0, 120.0])
    out = fine_summary(e)
    assert out["fine_mean_m"] == pytest.approx(sum(e) / 6) and out["fine_median_m"] == pytest.approx(2.95)
    assert [out[f"fine_within_{t}m"] for t in (1, 3, 5)] == pytest.approx([2 / 6, 4 / 6, 4 / 6])
    assert e2e_summary(e)["e2e_within_100m"] == pytest.approx(5 / 6)
    assert heading_summary([0.0, 10.0, 170.0])["fine_heading_median_deg"] == 10.0
    with pytest.raises(ValueError):
        fine_summary([1.0, float("nan")])


class FixedHeading(torch.nn.Module):
    """A stub refiner: every pair at its tile's centre, looking along 350°."""

    heading_bins = 36

    def match(self, query_maps, reference_maps, headings_deg):
        from geoloc.models.refiners import Refinement

        headings = torch.as_tensor(headings_deg, dtype=torch.float32)
        logits = torch.full((query_maps.shape[0], headings.numel(), 3, 3), -50.0)
        logits[:, int(torch.argmin(((headings - 350.0 + 180.0) % 360.0 - 180.0).abs())), 1, 1] = 0.0
        return Refinement(torch.log_softmax(logits.flatten(1), 1).view_as(logits), headings)


def test_the_refined_heading_error_wraps_around_north():
    """350° found for a truth of 10° is 20° off, not 340°."""
    from geoloc.tasks.crossview.refine import fine_metrics

    split = vigor_like([[0.0, 0.0]])
    refine = RefineConfig(orientation_noise_deg=180.0)
    candidates = refine.candidates(FixedHeading.heading_bins)
    maps = torch.zeros(1, 1, 2, 2)
    out = fine_metrics(FixedHeading(), split, refine, candidates, maps, maps, torch.tensor([10.0]),
                       top1=lambda: np.zeros(1, np.int64))
    assert out["fine_heading_median_deg"] == pytest.approx(20.0)
    assert out["fine_median_m"] == pytest.approx(0.0, abs=1e-6)


class FixedAnswers:
    """A refiner stand-in whose answer for each pair is the first two entries of its query map (a tile fraction)."""

    def match(self, query_maps, reference_maps, candidates):
        class Answer:
            def position(self):
                return query_maps[:, :2]

            def heading(self):
                return torch.zeros(len(query_maps))

            def mass_within(self, radius, extent):
                return torch.full((len(query_maps),), 0.5)

        return Answer()


def test_the_fine_metrics_skip_a_query_no_tile_shows_and_say_how_many(caplog):
    from geoloc.tasks.crossview.refine import fine_metrics, whole_tile_answers

    split = RetrievalSplit("own", "/r", ["q0", "q1", "q2"], ["t0", "t1"], positives=np.array([0, 1, 1]),
                           query_xy=[[1.0, 2.0], [50.0, 0.0], [120.0, 0.0]], reference_xy=[[0.0, 0.0], [50.0, 0.0]],
                           relevance_radius_m=25.0, radius_alone=True, reference_size_px=[[40, 40]] * 2,
                           reference_metres_per_px=[1.0, 1.0], query_tile_px=[[18.0, 21.0], [20.0, 20.0],
                                                                              [np.nan, np.nan]])
    assert np.isnan(split.query_tile_offset_m()[2]).all() and split.query_tile_offset_m()[0] == pytest.approx([1, 2])
    answers = torch.tensor([[0.5, 0.5], [0.5, 0.75], [0.1, 0.1]])  # 2.2 m and 10 m off; the third has no truth
    maps = torch.cat([answers, torch.zeros(3, 2)], dim=1)
    descriptors = torch.eye(3, 4), torch.eye(2, 4)
    with caplog.at_level("WARNING"):
        out = fine_metrics(FixedAnswers(), split, RefineConfig(), torch.zeros(1), maps, torch.zeros(2, 4),
                           torch.zeros(3), top1=lambda: top_k(*descriptors, 1)[1][:, 0].numpy())
    errors = [np.hypot(1.0, 2.0), 10.0]
    assert out["fine_mean_m"] == pytest.approx(np.mean(errors)) and out["fine_within_3m"] == 0.5
    assert "own: 1 of 3 queries lie in no tile" in caplog.text and "fine_*" in caplog.text
    assert out["e2e_within_100m"] == pytest.approx(2 / 3)  # end to end every query counts: its position is known
    mass, error, _, _ = whole_tile_answers(FixedAnswers(), RefineConfig(), split, torch.zeros(1), maps,
                                           torch.zeros(2, 4))
    assert error == pytest.approx(errors) and mass.shape == (2,)
    nowhere = RetrievalSplit("own", "/r", ["q2"], ["t0", "t1"], positives=np.array([1]), query_xy=[[120.0, 0.0]],
                             reference_xy=[[0.0, 0.0], [50.0, 0.0]], reference_size_px=[[40, 40]] * 2,
                             reference_metres_per_px=[1.0, 1.0], query_tile_px=[[np.nan, np.nan]])
    worst = fine_metrics(FixedAnswers(), nowhere, RefineConfig(), torch.zeros(1), maps[2:], torch.zeros(2, 4),
                         torch.zeros(1), top1=lambda: top_k(descriptors[0][2:], descriptors[1], 1)[1][:, 0].numpy())
    assert worst["fine_mean_m"] == float("inf") and worst["fine_within_1m"] == 0.0
