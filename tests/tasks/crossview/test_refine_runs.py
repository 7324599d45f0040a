"""The refiner in the cross-view task: a refinement stage from a retrieval checkpoint on a VIGOR-format tree (original
and corrected labels), an unknown heading, a plug-in refiner, the default run untouched, and a bad refiner
checkpoint refused."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from geoloc.config import ConfigError
from geoloc.engine import checkpoint as ckpt_io
from geoloc.launch import run
from geoloc.synthetic import generate
from geoloc.gallery.confidence import calibrators, fit_within, refine_features
from geoloc.tasks.crossview.encoder import CrossViewEncoder

from conftest import TINY, compose_evaluate, compose_train
from helpers.crossview_runs import task_of
from test_plugins import SEARCHPATH

BASE = [*TINY, "run_dir=unused"]  # a run dir that parsing names but nothing here writes
SMALL = [t for t in BASE if not t.startswith("dataset=")] + ["dataset=vigor", "dataset.check_files=exists",
                                                              "dataset.cities=[Chicago,NewYork]"]
REFINE = ["refiner=correlation", "refiner.channels=4", "refiner.width=4", "refiner.heading_bins=8",
          "refiner.size=32", "trainer.monitor=fine_median_m", "trainer.monitor_mode=min"]
FINE = ("fine_mean_m", "fine_median_m", "fine_within_1m", "fine_within_3m", "fine_within_5m")
E2E = ("e2e_median_m", "e2e_within_25m", "e2e_within_50m", "e2e_within_100m")


@pytest.fixture(scope="module")
def vigor_root(tmp_path_factory):
    return generate("vigor", tmp_path_factory.mktemp("vigor") / "ds", seed=3, preset="vigor_tiny", progress=False)


def corrected_copy(root, dest):
    """The tree with its split lists renamed as SliceMatch releases its corrected labels (splits__corrected)."""
    shutil.copytree(root, dest, symlinks=True)
    for path in (dest / "splits").rglob("*_balanced*.txt"):
        path.rename(path.with_name(path.stem + "__corrected.txt"))
    (dest / "splits").rename(dest / "splits__corrected")
    return dest


@pytest.mark.slow
def test_refinement_stage_from_a_retrieval_checkpoint(vigor_root, tmp_path):
    retrieval = tmp_path / "retrieval"
    run.train(compose_train([*SMALL, f"dataset.root={vigor_root}", "trainer.max_epochs=1", f"run_dir={retrieval}"]))
    refine_dir = tmp_path / "refine"
    best = run.train(compose_train([*SMALL, *REFINE, f"dataset.root={vigor_root}", "trainer.max_epochs=2",
                                    "dataset.calibration_holdout=3", f"init_from={retrieval / 'last.pt'}",
                                    f"run_dir={refine_dir}"]))
    for key in (*FINE, *E2E, "R@1", "median_m"):
        assert key in best, key
    assert "fine_heading_median_deg" not in best  # the heading is known
    # the retrieval network is as loaded: the refinement stage trains the refiner only
    source, refined = ckpt_io.load(retrieval / "last.pt")["task"], ckpt_io.load(refine_dir / "last.pt")["task"]
    assert all(torch.equal(source[k], refined[k]) for k in source if k.startswith("model."))
    assert any(k.startswith("refiner.") for k in refined)
    corrected = corrected_copy(vigor_root, tmp_path / "corrected")
    for root, labels in ((vigor_root, "splits"), (corrected, "splits__corrected")):
        out = tmp_path / f"{labels}.json"
        metrics = run.evaluate(compose_evaluate([f"ckpt={refine_dir / 'last.pt'}", "dataset=vigor",
                                                 f"dataset.root={root}", f"dataset.splits_dir={labels}",
                                                 "dataset.cities=[Chicago,NewYork]", f"metrics_out={out}",
                                                 "progress=false", f"run_dir={tmp_path / labels}"]))
        written = json.loads(out.read_text())
        assert written == pytest.approx(metrics)
        for key in (*FINE, *E2E):
            assert key in written and written[key] >= 0, key
        assert written["metre_labels"] == "synthetic"  # the renderer's exact truth, whatever the files are named
    assert json.loads((tmp_path / "splits.json").read_text()) == pytest.approx(
        json.loads((tmp_path / "splits__corrected.json").read_text()))  # the same labels under the other names

    # the apps answer in metres and degrees: the refined position in the top-1 tile, its heading and map, the picture
    from geoloc.apps.localize import Localizer, read_street
    from geoloc.apps.localize.picture import localization_figure
    from geoloc.data.geo import haversine_m

    gallery = tmp_path / "gallery"
    run.evaluate(compose_evaluate([f"ckpt={refine_dir / 'last.pt'}", "dataset=vigor", f"dataset.root={vigor_root}",
                                   "dataset.cities=[Chicago,NewYork]", f"gallery.save={gallery}", "progress=false",
                                   f"run_dir={tmp_path / 'saving'}"]))
    # the 3 held-out queries fit the refiner's P(within 5 m), or the record says why not (all right or all wrong)
    record = json.loads((gallery / "calibration.json").read_text())
    assert ("within_5m" in record.get("targets", {})) != ("refiner_why" in record)
    condition = CrossViewEncoder.load(refine_dir / "last.pt", device="cpu").refiner_condition
    if "within_5m" in record.get("targets", {}):  # fitted for this refiner: its weights and test keys
        assert record["targets"]["within_5m"]["condition"] == condition
    else:  # a calibrator of its own, to follow it into the answers
        record["targets"] = {**record.get("targets", {}), "within_5m": fit_within(
            [0.1, 0.4, 0.6, 0.9], [8.0, 3.0, 6.0, 1.0], 5.0, condition, "test").to_json()}
        (gallery / "calibration.json").write_text(json.dumps(record))
    localizer = Localizer.load(refine_dir / "last.pt", gallery, device="cpu")
    assert localizer.info()["calibration"]["within_5m"]["calibrated"] is True
    within = calibrators(record)["within_5m"]
    query = next(iter(localizer.places.queries.values()))
    answer = localizer.localize(read_street(vigor_root / query["path"]), topk=3, heading=0,
                                path=vigor_root / query["path"])
    out = answer.to_json()
    refined = out["refined_position"]
    assert set(refined) == {"lat", "lon", "heading_deg", "mass_5m", "confidence_within_5m", "tile_px",
                            "tile_size_px"}
    assert refined["confidence_within_5m"] == pytest.approx(
        within.probability(refine_features([refined["mass_5m"]]))[0], abs=1e-6)
    searched = localizer.localize(read_street(vigor_root / query["path"]), topk=3, heading="search").to_json()
    assert "confidence_within_5m" not in searched["refined_position"]  # a known-heading refiner, the heading searched
    assert 0.0 <= refined["mass_5m"] <= 1.0
    assert refined["heading_deg"] == 0.0  # trained with a known heading: the given one
    assert all("refined_position" in hit for hit in out["topk"])
    # inside its tile: no further from the top-1 tile's centre than the tile's half diagonal
    top1 = out["topk"][0]
    extent = localizer.places.reference_extent_m[top1["row"]]
    assert haversine_m([refined["lat"], refined["lon"]], [top1["lat"], top1["lon"]]) <= 0.5 * (extent ** 2).sum() ** 0.5 + 0.5
    # the page's dot: the same offset in the tile's pixels, metres per pixel = extent / size
    (row, col), (height, width) = refined["tile_px"], refined["tile_size_px"]
    metres = haversine_m([refined["lat"], refined["lon"]], [top1["lat"], top1["lon"]])
    pixels_m = np.hypot((row - height / 2) * extent[0] / height, (col - width / 2) * extent[1] / width)
    assert 0 <= row <= height and 0 <= col <= width and abs(pixels_m - metres) < 0.05 * metres + 0.05
    assert answer.probability_map.ndim == 2 and abs(answer.probability_map.sum() - 1.0) < 1e-4
    assert "refined_error_m" in out["truth"]
    picture = localization_figure(answer, read_street(vigor_root / query["path"]), localizer.places,
                                  tmp_path / "answer.png")
    assert picture.stat().st_size > 0


@pytest.mark.slow
def test_unknown_heading_reports_heading_errors_and_resumes(vigor_root, tmp_path):
    args = [*SMALL, *REFINE, f"dataset.root={vigor_root}", "refiner.orientation_noise_deg=180",
            "refiner.stage=joint", f"run_dir={tmp_path / 'run'}"]
    first = run.train(compose_train([*args, "trainer.max_epochs=1"]))
    assert {"fine_heading_mean_deg", "fine_heading_median_deg", *FINE} <= set(first)
    assert 0.0 <= first["fine_heading_median_deg"] <= 180.0
    resumed = run.train(compose_train([*args, "trainer.max_epochs=2", f"ckpt={tmp_path / 'run' / 'last.pt'}"]))
    assert "fine_heading_median_deg" in resumed
    # the gallery path reports the refiner's keys and values of the plain evaluation, the heading's included
    common = [f"ckpt={tmp_path / 'run' / 'last.pt'}", "dataset=vigor", f"dataset.root={vigor_root}",
              "dataset.cities=[Chicago,NewYork]", "progress=false"]
    plain = run.evaluate(compose_evaluate([*common, f"run_dir={tmp_path / 'plain'}"]))
    saved = run.evaluate(compose_evaluate([*common, f"gallery.save={tmp_path / 'gallery'}",
                                           f"run_dir={tmp_path / 'saving'}"]))
    refiner_keys = [k for k in plain if k.startswith(("fine_", "whole_tile_", "e2e_"))]
    assert {"fine_heading_median_deg", *FINE, *E2E} <= set(refiner_keys)
    assert {k: saved[k] for k in refiner_keys} == pytest.approx({k: plain[k] for k in refiner_keys}, abs=1e-4)


def test_the_default_run_has_no_refiner():
    cfg = compose_train(BASE)
    assert "refiner" not in cfg
    assert task_of(cfg).refiner is None


def test_a_plug_in_refiner_builds_and_trains_a_step(vigor_root):
    task = task_of(compose_train([*SMALL, SEARCHPATH, "refiner=dot_map", f"dataset.root={vigor_root}",
                                  "+refiner.orientation_noise_deg=180"]))
    assert type(task.refiner).__name__ == "DotMap"
    batch = {"refine_query": torch.randn(2, 3, 32, 32), "refine_reference": torch.randn(2, 3, 32, 32),
             "tile_px": torch.tensor([[0.4, 0.6], [0.5, 0.5]]), "refine_heading": torch.tensor([10.0, 200.0])}
    loss = task.training_step(batch, engine=None)["loss"]
    loss.backward()
    assert torch.isfinite(loss) and task.refiner.query_encoder.weight.grad is not None


def test_refiner_keys_are_checked_at_the_door():
    with pytest.raises(ValueError, match="orientation_noise_deg"):
        task_of(compose_train([*BASE, "refiner=correlation", "refiner.orientation_noise_deg=270"]))
    with pytest.raises(Exception, match="refiner"):
        task_of(compose_train([*BASE, "refiner=correlation", "+refiner.depth=3"]))


def test_a_bad_refiner_checkpoint_is_refused_with_the_keys(tmp_path):
    """A retrieval-only checkpoint, or one whose refiner has other shapes, given where a refiner is expected."""
    from geoloc.tasks.crossview.crossview_run import with_weights

    retrieval = task_of(compose_train(BASE))
    refining = task_of(compose_train([*BASE, "refiner=correlation"]))
    state = {"task": retrieval.state_dict(), "config": "{}"}
    with pytest.raises(ConfigError, match=r"missing.*refiner\."):
        with_weights(refining, state, tmp_path / "retrieval.pt")
    wider = task_of(compose_train([*BASE, "refiner=correlation", "refiner.channels=8"]))
    with pytest.raises(ConfigError, match=r"mis-shaped.*refiner\."):
        with_weights(refining, {"task": wider.state_dict(), "config": "{}"}, tmp_path / "wider.pt")


@pytest.mark.slow
def test_one_to_one_data_has_only_the_heading_to_find(tiny_cvusa, tmp_path):
    """CVUSA-layout pairs: the camera at the tile centre, the heading unknown; joint training from scratch."""
    best = run.train(compose_train([*BASE, f"dataset.root={tiny_cvusa}", "refiner=correlation", "refiner.channels=4",
                                    "refiner.width=4", "refiner.heading_bins=8", "refiner.stage=joint",
                                    "refiner.orientation_noise_deg=180", "trainer.max_epochs=1",
                                    f"run_dir={tmp_path / 'run'}"]))
    assert {"fine_heading_mean_deg", "fine_heading_median_deg", "R@1"} <= set(best)
    assert not any(key.startswith("e2e_") for key in best)  # one-to-one: no retrieved tile to refine in


@pytest.mark.slow
def test_a_refiner_with_a_margin_reads_the_tiles_beside_each_tile_end_to_end(vigor_root, tmp_path, monkeypatch):
    """refiner.margin=0.25: training, validation, the saved gallery and the localizer all give the refiner each tile
    with a quarter tile of ground around it, stitched from the tiles beside it (4 channels: RGB and coverage), and
    the answer stays in the tile's own pixels."""
    from geoloc.apps.localize import Localizer, read_street
    from geoloc.models.refiners.correlation import CorrelationRefiner

    seen = []
    encode = CorrelationRefiner.encode_reference
    monkeypatch.setattr(CorrelationRefiner, "encode_reference",
                        lambda self, images: seen.append(tuple(images.shape[1:])) or encode(self, images))
    run_dir = tmp_path / "run"
    best = run.train(compose_train([*SMALL, *REFINE, f"dataset.root={vigor_root}", "refiner.stage=joint",
                                    "refiner.semi_positives=true", "refiner.margin=0.25", "trainer.max_epochs=1",
                                    f"run_dir={run_dir}"]))
    assert {*FINE, "whole_tile_edge_median_m"} <= set(best)
    assert seen and set(seen) == {(4, 48, 48)}  # refiner.size 32 and 8 pixels beyond each edge, in every batch
    seen.clear()
    gallery = tmp_path / "gallery"
    run.evaluate(compose_evaluate([f"ckpt={run_dir / 'last.pt'}", "dataset=vigor", f"dataset.root={vigor_root}",
                                   "dataset.cities=[Chicago,NewYork]", f"gallery.save={gallery}", "progress=false",
                                   f"run_dir={tmp_path / 'saving'}"]))
    assert set(seen) == {(4, 48, 48)}
    seen.clear()
    localizer = Localizer.load(run_dir / "last.pt", gallery, device="cpu")
    query = next(iter(localizer.places.queries.values()))
    out = localizer.localize(read_street(vigor_root / query["path"]), topk=3, heading=0).to_json()
    assert set(seen) == {(4, 48, 48)}
    refined = out["refined_position"]
    tile = localizer.places.tile_image(out["topk"][0]["path"])
    assert refined["tile_size_px"] == list(tile.shape[:2])  # the tile's own pixels, not the stitched canvas's
    (row, col), (height, width) = refined["tile_px"], refined["tile_size_px"]
    assert 0 <= row <= height and 0 <= col <= width
