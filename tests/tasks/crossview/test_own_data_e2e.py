"""Your own data end to end (dataset=folder): fine-tune on the training area, evaluate, save a gallery, load it,
localize one image with localize.py and through the service; and the worked example of docs/datasets.md, built
from the real CVUSA samples (REALDATA) when they are present."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from geoloc.apps.localize import Localizer, read_street
from geoloc.data.geo import distance_m
from geoloc.datasets.folder import folder
from geoloc.launch import run
from hydra import compose, initialize_config_dir

from conftest import CONF, REALDATA, REPO, TINY, compose_evaluate, compose_train
from helpers.own_data import grid, write_folder

TILES = grid(4, 3, 60.0)
QUERIES = np.concatenate([TILES + [4.0, -3.0], TILES + [-6.0, 5.0]])  # two street images per tile
FOLDER_KEYS = ["dataset=folder", "dataset.tile_extent_m=40"]


def tiny(*extra):
    return [*(o for o in TINY if o != "dataset=cvusa"), *extra]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """(own-data root, checkpoint): TINY fine-tuned for one epoch on the training area of a random-image folder."""
    base = tmp_path_factory.mktemp("own")
    root = write_folder(base / "own", TILES, QUERIES, aerial=64, pano=(32, 128))
    run.train(compose_train(tiny(*FOLDER_KEYS, f"dataset.root={root}", f"run_dir={base / 'run'}",
                                 "trainer.max_epochs=1")))
    return root, base / "run" / "best.pt"


def localize_cfg(*overrides):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("localize", overrides=["device=cpu", "heading=0", "topk=3", *overrides])


@pytest.mark.slow
def test_fine_tune_evaluate_save_load_localize_and_serve_on_own_data(trained, tmp_path):
    from fastapi.testclient import TestClient
    from geoloc.apps.localize.command import localize
    from geoloc.apps.serve import create_app

    root, ckpt = trained
    state = json.loads((ckpt.parent / "metrics.jsonl").read_text().splitlines()[-1])
    test = folder(str(root), "test", tile_extent_m=40)
    assert test.name.startswith("folder/test (east >= ") and 0 < test.num_queries < len(QUERIES)
    assert "val/R@1" in state or any('"val/R@1"' in x for x in (ckpt.parent / "metrics.jsonl").read_text().splitlines())
    common = [f"ckpt={ckpt}", "progress=false", "device=cpu", *FOLDER_KEYS, f"dataset.root={root}",
              "dataset.split=all"]
    gallery = tmp_path / "gallery"
    plain = run.evaluate(compose_evaluate([*common, f"run_dir={tmp_path / 'e1'}"]))
    saved = run.evaluate(compose_evaluate([*common, f"run_dir={tmp_path / 'e2'}", f"gallery.save={gallery}"]))
    loaded = run.evaluate(compose_evaluate([*common, f"run_dir={tmp_path / 'e3'}", f"gallery.load={gallery}"]))
    assert plain["num_queries"] == len(QUERIES) and plain["num_references"] == len(TILES)
    for key in ("R@1", "R@5", "R@1%"):
        assert plain[key] == pytest.approx(saved[key]) == pytest.approx(loaded[key])
    unknown = run.evaluate(compose_evaluate([*common, f"run_dir={tmp_path / 'e4'}", "dataset.random_heading=true",
                                             "dataset.heading_steps=4", "dataset.fov=180"]))
    assert 0 <= unknown["heading_median_deg"] <= 180
    whole = folder(str(root), "all", tile_extent_m=40)
    image = whole.queries[5]
    answers = localize(localize_cfg(f"ckpt={ckpt}", f"gallery={gallery}", f"image={image}",
                                    f"out={tmp_path / 'answers'}"))
    answer = answers[0]
    truth = answer["truth"]
    assert truth["row"] == int(whole.positives[5]) and answer["positions"] == "latlon"
    top1 = (answer["position"]["lat"], answer["position"]["lon"])
    assert truth["error_m"] == pytest.approx(float(distance_m(whole.query_latlon[5], top1, "latlon")), abs=1e-6)
    served = TestClient(create_app(Localizer.load(ckpt, gallery, device="cpu"))).post(
        "/localize", files={"image": (image.name, image.read_bytes(), "image/png")}, data={"topk": "3", "heading": "0"})
    assert served.status_code == 200, served.text
    direct = Localizer.load(ckpt, gallery, device="cpu").localize(read_street(image), topk=3, heading=0.0,
                                                                   name=image.name)
    assert served.json() == json.loads(json.dumps(direct.to_json()))
    assert [hit["row"] for hit in served.json()["topk"]] == [hit["row"] for hit in answer["topk"]]


def example_tables() -> dict[str, str]:
    """The worked example's tables, as docs/datasets.md shows them."""
    text = (REPO / "docs" / "datasets.md").read_text()
    return {name: block for name, block in
            re.findall(r"<!-- own-data example: (\w+\.csv) -->\n```\n(.*?)```", text, flags=re.S)}


@pytest.mark.slow
@pytest.mark.skipif(not (REALDATA / "cvusa_mini").is_dir(), reason="../shared/realdata is absent")
def test_the_worked_example_of_the_docs_evaluates_and_localizes_the_real_samples(trained, tmp_path):
    from geoloc.apps.localize.command import localize

    _, ckpt = trained
    tables = example_tables()
    assert set(tables) == {"tiles.csv", "queries.csv"}
    own = tmp_path / "own"
    for side, source in (("queries", "streetview/panos"), ("tiles", "bingmap/19")):
        (own / side).mkdir(parents=True)
        for image in sorted((REALDATA / "cvusa_mini" / source).glob("*.jpg")):
            (own / side / image.name).symlink_to(image)  # linked, never copied
        (own / f"{side}.csv").write_text(tables[f"{side}.csv"])
    split = folder(str(own), "all", tile_extent_m=172.5)
    assert split.num_queries == split.num_references == 5 and split.positives.tolist() == [0, 1, 2, 3, 4]
    assert [len(r[r >= 0]) for r in split.relevance.relevant] == [1] * 5
    assert np.allclose(split.query_tile_px, [383.7, 388.0], atol=0.1)  # the docs state them to 0.1 px
    assert [p.name for p in folder(str(own), "test", tile_extent_m=172.5).references] == ["0000004.jpg",
                                                                                           "0000005.jpg"]
    gallery = tmp_path / "gallery"
    metrics = run.evaluate(compose_evaluate([
        f"ckpt={ckpt}", "progress=false", "device=cpu", f"run_dir={tmp_path / 'e'}", "dataset=folder",
        f"dataset.root={own}", "dataset.tile_extent_m=172.5", "dataset.split=all", f"gallery.save={gallery}"]))
    assert metrics["num_queries"] == metrics["num_references"] == 5
    answer = localize(localize_cfg(f"ckpt={ckpt}", f"gallery={gallery}", f"image={own / 'queries' / '0000003.jpg'}",
                                   f"out={tmp_path / 'answers'}"))[0]
    assert answer["truth"]["row"] == 2 and answer["truth"]["reference"] == "tiles/0000003.jpg"
    assert len(answer["topk"]) == 3 and "error_m" in answer["truth"] and "lat" in answer["position"]
