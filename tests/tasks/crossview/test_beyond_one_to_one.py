"""Training and evaluation on label-based splits end to end (synthetic VIGOR and University-1652 trees, read back
as released), the Sample4Geo components in a run, the monitored metric from config, and old checkpoints."""

from __future__ import annotations

import json

import pytest
import torch
from geoloc.config import ConfigError
from geoloc.engine import checkpoint as ckpt_io
from geoloc.launch import run
from geoloc.synthetic import generate
from omegaconf import OmegaConf

from conftest import TINY, compose_evaluate, compose_train
from helpers.crossview_runs import split_of

SMALL = [t for t in TINY if not t.startswith("dataset=")] + ["dataset.check_files=exists"]


def evaluate(tmp_path, *overrides):
    """run.evaluate with its own run dir (Hydra's, when run from the command line)."""
    run_dir = tmp_path / f"eval{len(list(tmp_path.glob('eval*')))}"
    return run.evaluate(compose_evaluate([*overrides, "progress=false", f"run_dir={run_dir}"]))


@pytest.fixture(scope="module")
def vigor_root(tmp_path_factory):
    return generate("vigor", tmp_path_factory.mktemp("vigor") / "ds", seed=3, preset="vigor_tiny", progress=False)


@pytest.fixture(scope="module")
def u1652_root(tmp_path_factory):
    return generate("u1652", tmp_path_factory.mktemp("u1652") / "ds", seed=1, preset="u1652_tiny", progress=False)


@pytest.mark.slow
def test_vigor_trains_and_evaluates_in_both_settings(vigor_root, tmp_path):
    """dataset=vigor dataset.root=DIR: validation and evaluate.py score the gallery of every tile of the test
    cities with R@K, the hit rate and metre errors; cross_area reads the other cities' lists."""
    cfg = compose_train([*SMALL, "dataset=vigor", f"dataset.root={vigor_root}", "dataset.cities=[Chicago,NewYork]",
                         "trainer.max_epochs=1", f"run_dir={tmp_path / 'run'}"])
    best = run.train(cfg)
    for key in ("R@1", "R@1%", "hit_rate", "median_m", "within_10m", "within_25m", "within_50m"):
        assert key in best, key
    assert best["hit_rate"] >= best["R@1"]  # a positive at the top is a hit
    for setting, cities in (("same_area", "[Chicago,NewYork]"), ("cross_area", "[Chicago]")):
        out = tmp_path / f"{setting}.json"
        metrics = evaluate(tmp_path, f"ckpt={tmp_path / 'run' / 'best.pt'}", "dataset=vigor",
                           f"dataset.root={vigor_root}", f"dataset.setting={setting}", f"dataset.cities={cities}",
                           f"metrics_out={out}")
        written = json.loads(out.read_text())
        assert written == pytest.approx(metrics)
        assert written["num_queries"] > 0 and 0.0 <= written["hit_rate"] <= 1.0
    same = json.loads((tmp_path / "same_area.json").read_text())
    cross = json.loads((tmp_path / "cross_area.json").read_text())
    # vigor_tiny: 3 test panoramas per city, 9 tiles per city; cross-area test = Chicago's whole list (train + test)
    assert (same["num_queries"], same["num_references"]) == (6, 18)
    assert (cross["num_queries"], cross["num_references"]) == (7, 9)

    # a saved gallery of this non-1:1 split scores as the exact evaluation, and localize answers from it
    ckpt, folder = tmp_path / "run" / "best.pt", tmp_path / "gallery"
    args = (f"ckpt={ckpt}", "dataset=vigor", f"dataset.root={vigor_root}", "dataset.cities=[Chicago,NewYork]")
    saved = evaluate(tmp_path, *args, f"gallery.save={folder}")
    loaded = evaluate(tmp_path, *args, f"gallery.load={folder}")
    for key in ("R@1", "R@5", "R@1%", "hit_rate", "median_m", "within_50m"):
        assert saved[key] == pytest.approx(same[key]) and loaded[key] == pytest.approx(same[key]), key
    from geoloc.apps.localize import Localizer, read_street
    from geoloc.data.geo import haversine_m

    query = json.loads((folder / "queries.jsonl").read_text().splitlines()[0])
    answer = Localizer.load(ckpt, folder, device="cpu").localize(
        read_street(vigor_root / query["path"]), topk=3, heading=0, path=vigor_root / query["path"]).to_json()
    top1 = answer["topk"][0]
    assert answer["truth"]["row"] == query["positive"] and answer["positions"] == "latlon"
    assert answer["truth"]["error_m"] == pytest.approx(
        float(haversine_m([query["lat"], query["lon"]], [top1["lat"], top1["lon"]])))


@pytest.mark.slow
def test_u1652_trains_and_scores_both_directions_with_ap(u1652_root, tmp_path):
    cfg = compose_train([*SMALL, "dataset=u1652", f"dataset.root={u1652_root}", "trainer.max_epochs=1",
                         "sampler=no_duplicate", "dataset.batch_size=3", f"run_dir={tmp_path / 'run'}"])
    best = run.train(cfg)
    assert "AP" in best and 0.0 < best["AP"] <= 1.0
    for direction in ("drone_to_satellite", "satellite_to_drone"):
        metrics = evaluate(tmp_path, f"ckpt={tmp_path / 'run' / 'best.pt'}", "dataset=u1652",
                           f"dataset.root={u1652_root}", f"dataset.direction={direction}")
        assert {"R@1", "AP", "num_queries"} <= set(metrics) and 0.0 <= metrics["AP"] <= 1.0
        # u1652_tiny: 2 query buildings of 3 drone views; the gallery adds 1 building no query shows (a distractor)
        assert (metrics["num_queries"], metrics["num_references"]) == ((6, 3) if direction[0] == "d" else (2, 9))


def test_photo_queries_refuse_polar_alignment(u1652_root, tmp_path):
    cfg = compose_train([*SMALL, "dataset=u1652", f"dataset.root={u1652_root}", "dataset.alignment=ipt"])
    with pytest.raises(ConfigError, match="photo queries .* dataset.alignment=none"):
        split_of(cfg.dataset, "train")


def test_the_tile_alone_turns_for_photo_queries_and_never_for_panoramas(u1652_root, tiny_cvusa):
    """dataset.aerial_rotation_deg: University-1652's satellite rotation, drawn per item from (seed, epoch, index);
    the drone photo is untouched, and a panorama dataset refuses it (the tile would leave north)."""
    import numpy as np
    from geoloc.config import ConfigError
    from geoloc.tasks.crossview.transforms import rotate_about_centre

    from helpers.crossview_runs import pairs_of

    base = [*SMALL, "dataset=u1652", f"dataset.root={u1652_root}"]
    plain = pairs_of(compose_train(base).dataset, "train", train=True)
    turned = pairs_of(compose_train([*base, "dataset.aerial_rotation_deg=90"]).dataset, "train", train=True)
    a, b = plain[(0, 0)], turned[(0, 0)]
    assert torch.equal(a["query"], b["query"]) and not torch.equal(a["reference"], b["reference"])
    assert torch.equal(b["reference"], turned[(0, 0)]["reference"])  # keyed on the item: the same draw again
    assert not torch.equal(b["reference"], turned[(0, 1)]["reference"])  # another epoch, another angle
    square = np.zeros((9, 9, 3), np.uint8)
    square[4, 6] = 255  # two pixels east of the centre, turned 90° counter-clockwise: two pixels north of it
    assert rotate_about_centre(square, 90.0)[2, 4].tolist() == [255, 255, 255]
    assert np.array_equal(rotate_about_centre(square, 0.0), square)
    cfg = compose_train([*TINY, f"dataset.root={tiny_cvusa}", "dataset.aerial_rotation_deg=30"])
    with pytest.raises(ConfigError, match="panorama queries: dataset.aerial_rotation_deg"):
        split_of(cfg.dataset, "train")


@pytest.mark.slow
def test_infonce_with_a_learned_temperature_and_similarity_batches(tiny_cvusa, tmp_path, monkeypatch):
    """loss=infonce sampler=similarity: the temperature is optimised with the network, and from the second epoch
    the sampler is given the training pairs' descriptors."""
    from geoloc.data import samplers

    given = []
    real = samplers.SimilarityBatches.set_descriptors

    def spy(self, query, reference):
        given.append((query.shape, reference.shape))
        return real(self, query, reference)

    monkeypatch.setattr(samplers.SimilarityBatches, "set_descriptors", spy)
    no_loss = [t for t in TINY if not t.startswith("loss")]
    cfg = compose_train([*no_loss, f"dataset.root={tiny_cvusa}", "loss=infonce", "optim=adamw", "sampler=similarity",
                         "sampler.neighbour_select=1", "sampler.neighbour_range=2", "trainer.max_epochs=2",
                         f"run_dir={tmp_path / 'run'}"])
    run.train(cfg)
    assert given == [(torch.Size([12, 16]), torch.Size([12, 16]))]  # epoch 1 only; 12 training pairs, dim 16
    state = ckpt_io.load(tmp_path / "run" / "last.pt")
    assert state["task"]["loss.log_inv_temperature"] != pytest.approx(torch.tensor(1 / 0.07).log().item(), abs=1e-7)


@pytest.mark.slow
def test_the_monitored_metric_and_its_mode_come_from_config(tiny_cvusa, tmp_path):
    """trainer.monitor picks the metric that selects best.pt; monitor_mode=min keeps the lowest."""
    bests = {}
    for mode in ("max", "min"):
        cfg = compose_train([*TINY, f"dataset.root={tiny_cvusa}", "trainer.max_epochs=3", "trainer.monitor=R@5",
                             f"trainer.monitor_mode={mode}", f"run_dir={tmp_path / mode}"])
        bests[mode] = run.train(cfg)
    records = [json.loads(x) for x in (tmp_path / "max" / "metrics.jsonl").read_text().splitlines()
               if '"val/R@5"' in x]
    values = [r["val/R@5"] for r in records]
    assert bests["max"]["R@5"] == max(values) and bests["min"]["R@5"] == min(values)
    assert bests["max"]["epoch"] == values.index(max(values))  # the first epoch that reached it
    cfg = compose_train([*TINY, f"dataset.root={tiny_cvusa}", "trainer.monitor=AP", f"run_dir={tmp_path / 'x'}",
                         "trainer.max_epochs=1"])
    with pytest.raises(ConfigError, match="trainer.monitor='AP' is not a metric that validation reports on cvusa/val"):
        run.train(cfg)  # before the first epoch (validation_keys.py)


@pytest.mark.slow
def test_a_checkpoint_of_the_old_layout_still_evaluates(finished_run, tmp_path):
    """Checkpoints written before the registry (model: {name: msae_vgg16, ...}, queue.* keys) are read into the new
    layout and score the same."""
    root, finished = finished_run
    state = ckpt_io.load(finished / "best.pt")
    cfg = OmegaConf.create(state["config"])
    cfg.head.scale_activation = "relu"  # the old layout's MSAE, which had no such key, ends its branches in a ReLU
    torch.save({**state, "config": OmegaConf.to_yaml(cfg)}, tmp_path / "relu.pt")
    new = evaluate(tmp_path, f"ckpt={tmp_path / 'relu.pt'}", f"dataset.root={root}")
    old = OmegaConf.to_container(cfg)
    backbone, head = old.pop("backbone"), old.pop("head")
    old["model"] = {"name": "msae_vgg16", **{k: v for k, v in backbone.items() if k != "name"},
                    "msae": head["name"] == "msae", "dim": old["model"]["dim"],
                    **{k: v for k, v in head.items() if k not in ("name", "scale_activation")}}
    old.pop("sampler")
    old_state = {**state, "config": OmegaConf.to_yaml(OmegaConf.create(old)),
                 "task": {k.replace("loss.queue.", "queue."): v for k, v in state["task"].items()}}
    torch.save(old_state, tmp_path / "old.pt")
    again = evaluate(tmp_path, f"ckpt={tmp_path / 'old.pt'}", f"dataset.root={root}")
    assert again == new


@pytest.mark.parametrize("name,layout", [("synthetic", "cvusa"), ("vigor", "vigor"), ("u1652", "u1652"),
                                         ("dynamic", "dynamic")])
def test_embedded_datasets_render_into_the_cache_when_root_is_null(name, layout, tmp_path, monkeypatch):
    """root=null reaches the synthetic renderer for every embedded dataset (the readers and task=mmdip's)."""
    import geoloc.synthetic as synthetic

    asked = []

    def fake_ensure(kind, root, **kwargs):
        asked.append((kind, root))
        raise RuntimeError("stop here")

    monkeypatch.setenv("GEOLOC_CACHE", str(tmp_path))
    monkeypatch.setattr(synthetic, "ensure_dataset", fake_ensure)
    with pytest.raises(RuntimeError, match="stop here"):
        if name == "dynamic":
            from geoloc.tasks.mmdip.mmdip_config import data_config
            from geoloc.tasks.mmdip.readers import build_reader

            build_reader(data_config(compose_train(["task=mmdip"]).dataset))
        else:
            

            split_of(compose_train([f"dataset={name}"]).dataset, "train")
    assert asked[0][0] == layout and str(asked[0][1]).startswith(str(tmp_path / "synthetic"))


def test_figures_frame_retrievals_by_label():
    """top5.png's frames: the positive green, a semi-positive orange (VIGOR), any reference of the query's building
    green with labels (University-1652), the rest red; one-to-one: reference i for query i."""
    import numpy as np
    from geoloc.data.retrieval_split import RetrievalSplit
    from geoloc.tasks.crossview.figures import GREEN, ORANGE, RED, relevance_colour

    vigor = RetrievalSplit("v", "/r", ["q0", "q1"], ["r0", "r1", "r2"], positives=np.array([2, 0]),
                           semi_positives=np.array([[1, -1], [-1, -1]]))
    assert [relevance_colour(vigor, 0, j) for j in range(3)] == [RED, ORANGE, GREEN]
    assert [relevance_colour(vigor, 1, j) for j in range(3)] == [GREEN, RED, RED]
    u1652 = RetrievalSplit("u", "/r", ["q0"], ["r0", "r1", "r2"], positives=np.array([1]),
                           query_labels=np.array([7]), reference_labels=np.array([3, 7, 7]))
    assert [relevance_colour(u1652, 0, j) for j in range(3)] == [RED, GREEN, GREEN]
    assert relevance_colour(None, 4, 4) == GREEN and relevance_colour(None, 4, 5) == RED


@pytest.mark.slow
def test_figures_are_written_for_a_label_based_split(u1652_root, tmp_path):
    cfg = compose_train([*SMALL, "dataset=u1652", f"dataset.root={u1652_root}", "trainer.max_epochs=1",
                         "figures=true", f"run_dir={tmp_path / 'run'}"])
    run.train(cfg)
    for name in ("attention.png", "top5.png", "recall_curve.png"):
        assert (tmp_path / "run" / name).stat().st_size > 1000, name
