"""`geoloc robustness`: every cell of its table equals a separate evaluate.py run of the same condition (a padded
gallery through a reader that builds it independently); its files are written whole and never replaced unasked."""

from __future__ import annotations

import json

import numpy as np
import pytest
from geoloc.apps.robustness.command import RobustnessConfig, robustness, split_args
from geoloc.config import ConfigError
from geoloc.launch.hydra_hooks import compose_checked
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.datasets.cvusa import cvusa
from geoloc.launch import run
from geoloc.registry import register

from conftest import TINY, compose_evaluate, compose_train, write_cvusa

DISTRACTORS = 5


@register("dataset", "robustness_padded_test")
def padded_test(root: str, split: str) -> RetrievalSplit:
    """CVUSA's `split` with the first DISTRACTORS train tiles appended to its gallery, built without datasets.padded."""
    own, train = cvusa(root, split), cvusa(root, "train")
    return RetrievalSplit("padded_test", root, own.queries, own.references + train.references[:DISTRACTORS],
                          np.arange(own.num_queries))


@register("dataset", "robustness_same_area")
def same_area(root: str, split: str) -> RetrievalSplit:
    """CVUSA's `split` whose gallery is every tile of train and val, as each split of VIGOR same-area holds every
    tile of the four cities."""
    own, other = cvusa(root, split), cvusa(root, "val" if split == "train" else "train")
    return RetrievalSplit("same_area", root, own.queries, own.references + other.references,
                          np.arange(own.num_queries))


@register("dataset", "robustness_overlap")
def overlap(root: str, split: str) -> RetrievalSplit:
    """CVUSA, whose train gallery also holds the first 3 val tiles."""
    own, val = cvusa(root, split), cvusa(root, "val")
    shared = val.references[:3] if split == "train" else []
    return RetrievalSplit("overlap", root, own.queries, shared + own.references,
                          np.arange(own.num_queries) + len(shared))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    base = tmp_path_factory.mktemp("robustness")
    root, other = write_cvusa(base / "cvusa", n_train=12, n_val=8), write_cvusa(base / "other", 4, 6, seed=1)
    run.train(compose_train([*TINY, f"dataset.root={root}", f"run_dir={base / 'run'}", "trainer.max_epochs=1"]))
    return base, root, other, base / "run" / "best.pt"


@pytest.mark.slow
def test_every_cell_is_what_evaluate_py_gives_for_its_condition(trained):
    base, root, other, ckpt = trained
    out = base / "table"
    record = robustness([f"ckpt={ckpt}", f"out={out}", "fovs=[360,90]", "heading_steps=4",
                         f"distractors={DISTRACTORS}", f"cross=dataset=cvusa dataset.root={other}", "device=cpu"])
    assert json.loads((out / "robustness.json").read_text()) == json.loads(json.dumps(record))
    table = (out / "robustness.md").read_text()
    rows = record["rows"]
    assert [(r["fov"], r["heading"], r["distractors"], r["cross_dataset"]) for r in rows] == [
        (f, h, d, False) for d in (0, DISTRACTORS) for f in (360.0, 90.0) for h in ("known", "unknown")] + [
        (360.0, "known", 0, True)]
    for k, row in enumerate(rows):
        data = (["+dataset.name=robustness_padded_test", f"dataset.root={root}"] if row["distractors"]
                else [f"dataset.root={other}"] if row["cross_dataset"] else [])
        alone = run.evaluate(compose_evaluate([
            f"ckpt={ckpt}", "progress=false", "device=cpu", f"run_dir={base / f'eval{k}'}", *data,
            f"dataset.fov={row['fov']}", f"dataset.random_heading={row['heading'] == 'unknown'}",
            "dataset.heading_steps=4"]))
        for key in ("R@1", "R@5", "R@1%", "heading_median_deg", "num_references", "num_queries"):
            assert row["metrics"].get(key) == pytest.approx(alone.get(key)), (row, key)
        assert ("heading_median_deg" in alone) == (row["heading"] == "unknown")
        assert alone["num_references"] == (6 if row["cross_dataset"] else 8 + row["distractors"])
        cells = f"| {row['fov']:g} | {row['heading']} | " + " | ".join(
            f"{100 * alone[key]:.2f}" for key in ("R@1", "R@5", "R@1%"))
        assert cells in table
    with pytest.raises(ConfigError, match="already exist; choose another out=, or overwrite=true"):
        robustness([f"ckpt={ckpt}", f"out={out}", "fovs=[360]", "distractors=0", "cross=none"])


def test_the_arguments_split_into_the_commands_keys_and_evaluate_overrides():
    own, dataset, cross = split_args(["ckpt=a.pt", "dataset=cvact", "dataset.root=/d", "heading_steps=6",
                                      "cross=dataset=vigor dataset.setting=cross_area;dataset=u1652"])
    assert own == ["ckpt=a.pt", "heading_steps=6"] and dataset == ["dataset=cvact", "dataset.root=/d"]
    assert cross == [["dataset=vigor", "dataset.setting=cross_area"], ["dataset=u1652"]]
    assert split_args(["ckpt=a.pt"])[2] == [["dataset=vigor"]] and split_args(["cross=none"])[2] == []


def test_the_commands_own_keys_take_hydras_grammar_and_a_bad_one_is_refused_naming_it(tmp_path):
    """geoloc/conf/robustness.yaml over RobustnessConfig, composed as the other verbs compose theirs: a list, Hydra's
    quoting (a comma kept in a path), `+key`, a typo and an argument without `=`, each before anything runs."""
    cfg = compose_checked("robustness", RobustnessConfig, ["ckpt=a.pt", "fovs=[360,90]", "distractor_split='val'",
                                                           "out='runs/a,b'"], "robustness")
    assert cfg == RobustnessConfig(ckpt="a.pt", fovs=[360.0, 90.0], distractor_split="val", out="runs/a,b")
    assert compose_checked("robustness", RobustnessConfig, ["ckpt=a.pt"], "robustness") == RobustnessConfig(ckpt="a.pt")
    absent = f"ckpt={tmp_path / 'absent.pt'}"
    for arg, says in (("fovz=[90]", "Could not override 'fovz'.$"), ("+fovz=[90]", "Key 'fovz' not in 'Robustness"),
                      ("fovs", "Error parsing override 'fovs' missing EQUAL"), ("out=a,b", "Ambiguous value")):
        with pytest.raises(ConfigError, match=f"^bad 'robustness' config: {says}"):
            robustness([absent, "cross=dataset=cvusa dataset.root=/d", "dataset.split=val", arg])


def test_a_taken_out_folder_or_a_missing_checkpoint_is_refused_before_anything_runs(tmp_path):
    (tmp_path / "robustness.md").write_text("mine")
    with pytest.raises(ConfigError, match="robustness.md already exist"):
        robustness([f"ckpt={tmp_path / 'absent.pt'}", f"out={tmp_path}"])
    assert (tmp_path / "robustness.md").read_text() == "mine"
    with pytest.raises(ConfigError, match="is not a file"):
        robustness([f"ckpt={tmp_path / 'absent.pt'}", f"out={tmp_path / 'new'}"])
    # out= an existing file, or below one (was: every row evaluated, then a bare FileExistsError and no table)
    (tmp_path / "notes.txt").write_text("mine")
    for out in (tmp_path / "notes.txt", tmp_path / "notes.txt" / "table"):
        for overwrite in ("false", "true"):
            with pytest.raises(ConfigError, match=rf"out={out}: {tmp_path / 'notes.txt'} is a file, not a folder"):
                robustness([f"ckpt={tmp_path / 'absent.pt'}", f"out={out}", f"overwrite={overwrite}"])
    assert (tmp_path / "notes.txt").read_text() == "mine"
    with pytest.raises(ConfigError, match=r"fovs must be a non-empty list of degrees in \(0, 360\]"):
        robustness([f"ckpt={tmp_path / 'absent.pt'}", "fovs=[400]"])


def test_distractors_are_tiles_outside_the_evaluated_gallery_checked_before_any_row(trained, monkeypatch):
    """The default distractor_split=train on a dataset whose splits share their tiles (VIGOR same-area): the shared
    tiles are no distractors, and where none is left the padded rows are left out with a note; a distractor split
    that cannot pad is refused before the first row is scored."""
    from geoloc.apps.robustness import conditions

    base, root, _, ckpt = trained
    scored = []
    score = conditions.score
    monkeypatch.setattr(conditions, "score", lambda *args: scored.append(1) or score(*args))
    common = [f"ckpt={ckpt}", f"dataset.root={root}", "fovs=[360]", "heading_steps=4", "distractors=5",
              "cross=none", "device=cpu"]
    with pytest.raises(ConfigError, match="distractor_split=val is the evaluated split itself"):
        robustness([*common, "+dataset.name=robustness_overlap", "distractor_split=val", f"out={base / 'refused'}"])
    assert scored == [] and not (base / "refused").exists()

    record = robustness([*common, "+dataset.name=robustness_same_area", f"out={base / 'same_area'}"])
    assert [(r["fov"], r["heading"], r["distractors"]) for r in record["rows"]] == [(360, "known", 0),
                                                                                    (360, "unknown", 0)]
    note = ("No padded rows: every tile of distractor_split=train (20) is in the evaluated gallery of same_area, so "
            "none shows another place")
    assert record["notes"][0].startswith(note) and note in (base / "same_area" / "robustness.md").read_text()

    record = robustness([*common, "+dataset.name=robustness_overlap", f"out={base / 'overlap'}"])
    padded = [r for r in record["rows"] if r["distractors"]]
    assert len(padded) == 2 and all(r["distractors"] == 5 and r["metrics"]["num_references"] == 13 for r in padded)
    assert record["notes"] == ["The 3 tiles of distractor_split=train that are in the evaluated gallery of overlap "
                               "are not distractors: the padding is drawn from its 12 others."]
