"""`geoloc bench`: every cell equals evaluate.py's figure for its checkpoint, test set and protocol, digit for digit,
though the references are encoded once; checkpoints come from files, run folders and sweeps; the published figures
stand beside the rows of their protocol only."""

from __future__ import annotations

import csv
import json
import os

import pytest
import yaml
from geoloc.apps.bench.checkpoints import checkpoints
from geoloc.apps.bench.command import BenchConfig, bench, split_args
from geoloc.apps.bench.published import matching, published
from geoloc.apps.bench.bench_sets import TEST_SETS, data_overrides
from geoloc.config import ConfigError
from geoloc.launch import run
from geoloc.launch.hydra_hooks import compose_checked

from conftest import TINY, compose_evaluate, compose_train, write_cvusa

KEYS = ("R@1", "R@5", "R@10", "R@1%", "heading_median_deg", "num_queries", "num_references")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    base = tmp_path_factory.mktemp("bench")
    root = write_cvusa(base / "cvusa", n_train=12, n_val=8)
    run.train(compose_train([*TINY, f"dataset.root={root}", f"run_dir={base / 'run'}", "trainer.max_epochs=1"]))
    return base, root, base / "run" / "best.pt"


@pytest.mark.slow
def test_every_cell_is_what_evaluate_py_gives_for_its_protocol(trained):
    base, root, ckpt = trained
    out = base / "table"
    record = bench([f"ckpts=[{ckpt.parent}]", "sets=[cvusa]", f"cvusa={root}", "fovs=[360,90]", "heading_steps=4",
                    f"out={out}", "device=cpu", "progress=false"])
    rows = record["rows"]
    assert [(r["fov"], r["heading"], r["synthetic"]) for r in rows] == [
        (f, h, False) for f in (360.0, 90.0) for h in ("known", "unknown")]
    for k, row in enumerate(rows):
        alone = run.evaluate(compose_evaluate([
            f"ckpt={ckpt}", "progress=false", "device=cpu", f"run_dir={base / f'eval{k}'}", "dataset=cvusa",
            f"dataset.root={root}", "dataset.split=val", f"dataset.fov={row['fov']}",
            f"dataset.random_heading={row['heading'] == 'unknown'}", "dataset.heading_steps=4"]))
        assert {key: row["metrics"].get(key) for key in KEYS} == {key: alone.get(key) for key in KEYS}, row
    assert json.loads((out / "bench.json").read_text()) == json.loads(json.dumps(record))
    table = (out / "bench.md").read_text()
    known360 = next(r for r in rows if r["fov"] == 360.0 and r["heading"] == "known")
    assert f"| run | cvusa | released | FoV 360, heading known | 8 | 8 | {100 * known360['metrics']['R@1']:.2f} |" \
        in table
    assert "MSAE 81.39 [1]; Sample4Geo 98.68 [2]" in table and "[1] MSAE: Li, Tu, Chen, Yu." in table
    lines = list(csv.reader((out / "bench.csv").read_text().splitlines()))
    assert len(lines) == 1 + len(rows) and lines[1][:4] == ["run", "cvusa", "released", "FoV 360, heading known"]
    with pytest.raises(ConfigError, match="already exist; choose another out=, or overwrite=true"):
        bench([f"ckpts=[{ckpt}]", f"out={out}"])


def test_a_sweep_folder_gives_each_runs_best_pt_named_by_its_overrides(trained, tmp_path):
    _, _, ckpt = trained
    for seed in (0, 1):
        job = tmp_path / "sweep" / str(seed)
        (job / ".hydra").mkdir(parents=True)
        (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"seed={seed}", "dataset=cvusa"]))
        os.link(ckpt, job / "best.pt")
    assert checkpoints([str(tmp_path / "sweep"), str(ckpt)]) == [
        ("seed=0", tmp_path / "sweep" / "0" / "best.pt"), ("seed=1", tmp_path / "sweep" / "1" / "best.pt"),
        ("run", ckpt)]
    with pytest.raises(ConfigError, match="holds no best.pt"):
        checkpoints([str(tmp_path / "sweep" / "0" / ".hydra")])


def test_test_sets_read_a_given_root_or_their_embedded_world():
    assert data_overrides(TEST_SETS["cvusa"], {"cvusa": "/data/CVUSA"}) == (
        ["dataset=cvusa", "dataset.split=val", "dataset.root=/data/CVUSA"], False)
    assert data_overrides(TEST_SETS["cvusa"], {}) == (["dataset=synthetic", "dataset.split=val"], True)
    assert data_overrides(TEST_SETS["vigor_cross"], {}) == (
        ["dataset=vigor", "dataset.setting=cross_area", "dataset.root=null"], True)
    # VIGOR's two label sets: the corrected ones where the root holds them, the original ones named
    assert data_overrides(TEST_SETS["vigor_same_original"], {"vigor": "/data/VIGOR"}) == (
        ["dataset=vigor", "dataset.setting=same_area", "dataset.splits_dir=splits", "dataset.root=/data/VIGOR"], False)
    assert TEST_SETS["vigor_same_original"].published_as == "vigor_same" == TEST_SETS["vigor_same"].published_as
    assert split_args(["sets=[cvusa]", "dataset.max_val=4"]) == (["sets=[cvusa]"], ["dataset.max_val=4"])
    with pytest.raises(ConfigError, match="dataset= is not a geoloc bench key"):
        split_args(["dataset=vigor"])


def test_the_commands_keys_take_hydras_grammar_and_a_bad_one_is_refused_before_anything_runs(tmp_path):
    """geoloc/conf/bench.yaml over BenchConfig, composed as the other verbs compose theirs."""
    assert compose_checked("bench", BenchConfig, [], "bench") == BenchConfig()
    cfg = compose_checked("bench", BenchConfig, ["ckpts=[a/best.pt,'b,1']", "headings=[unknown]"], "bench")
    assert cfg.ckpts == ["a/best.pt", "b,1"] and cfg.headings == ["unknown"]  # quoted: a comma kept in a path
    for arg, says in (("fovz=[90]", "Could not override 'fovz'.$"), ("+fovz=[90]", "Key 'fovz' not in 'BenchConfig'"),
                      ("sets", "Error parsing override 'sets' missing EQUAL")):
        with pytest.raises(ConfigError, match=f"^bad 'bench' config: {says}"):
            bench([f"ckpts=[{tmp_path / 'absent.pt'}]", f"out={tmp_path / 'out'}", "dataset.max_val=4", arg])
    assert not (tmp_path / "out").exists()


def test_every_published_figure_names_its_source_and_protocol():
    anchors = published()["anchors"]
    assert anchors and all({"method", "paper", "where", "test_set", "fov", "heading", "metrics"} <= set(a)
                           for a in anchors)
    assert all(a["test_set"] in TEST_SETS and a["heading"] in ("known", "unknown") for a in anchors)
    assert [a["method"] for a in matching("vigor_same", 360, "known")] == ["Sample4Geo"]
    assert matching("cvusa", 90, "known") == []  # a figure stands beside its own protocol only


def test_the_original_labels_need_a_released_root_and_share_the_published_figures(trained, tmp_path):
    from geoloc.apps.bench.report import published_beside

    _, _, ckpt = trained
    record = bench([f"ckpts=[{ckpt}]", "sets=[vigor_same_original,vigor_cross_original]", f"out={tmp_path / 'o'}",
                    "device=cpu", "progress=false"])
    assert record["rows"] == []
    assert record["notes"][0].startswith("vigor_same_original, vigor_cross_original: VIGOR's original labels, "
                                         "scored on a released root alone (vigor=DIR)")
    row = {"test_set": "vigor_same_original", "published_as": "vigor_same", "fov": 360.0, "heading": "known"}
    assert published_beside(row) == matching("vigor_same", 360.0, "known")
