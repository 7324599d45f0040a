"""evaluate.py of MMDIP checkpoints, without training: a phase-2 evaluation writes its vocabulary, gallery and
metrics to its own run dir and reuses the training run's, read only, when they match; it never writes into the
training run, nor beside a copied checkpoint. A phase-1 checkpoint prints its table (PA, MPA, MIoU, FWIoU and
per-class IoU), as phase 2 prints its recall table."""

import shutil

import pytest
import torch
from geoloc.config import ConfigError, to_yaml
from geoloc.engine import checkpoint as ckpt_io
from geoloc.tasks.mmdip.mmdip_config import data_config, task_config
from geoloc.tasks.mmdip.datasets import NUM_CLASSES, STATIC_CLASSES
from geoloc.tasks.mmdip.joint import JointTask
from geoloc.tasks.mmdip.pipeline import load_task, vpr_dir
from geoloc.tasks.mmdip.readers import build_reader
from geoloc.tasks.mmdip.retrieval import evaluate_retrieval, model_id
from geoloc.tasks.mmdip.segmentation import SegmentationTask

from conftest import compose_train
from helpers.dynamic_data import TINY_MMDIP, evaluate, write_tiny_dynamic

TINY = [*TINY_MMDIP, "task.translation.num_downs=2", "dataset.image_size=[32,32]"]


def write_checkpoint(run, root, phase: int):
    """RUN/phase<phase>/best.pt as the trainer writes it, untrained: the evaluation's paths do not depend on the
    weights."""
    cfg = compose_train([*TINY, f"dataset.root={root}", f"run_dir={run}"])
    task_cfg = task_config(cfg.task)
    torch.manual_seed(0)
    uniform = [1 / NUM_CLASSES] * NUM_CLASSES
    task = (JointTask(task_cfg, uniform, training=False) if phase == 2
            else SegmentationTask(task_cfg.segmentation, NUM_CLASSES, uniform))
    path = run / f"phase{phase}" / "best.pt"
    path.parent.mkdir(parents=True)
    ckpt_io.save_atomic({"task": task.state_dict(), "config": to_yaml(cfg), "epoch": 0}, path)
    return path


def evaluation(root, run_dir=None):
    return compose_train([*TINY, f"dataset.root={root}", *([f"run_dir={run_dir}"] if run_dir else [])])


def snapshot(folder):
    return {p.relative_to(folder): (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))
            if p.is_file()}


@pytest.fixture
def trained(tmp_path, one_thread):
    """(data root, run dir, phase-2 checkpoint, its recall) with the training run's vpr/ records in place, written
    as train() writes them."""
    root = write_tiny_dynamic(tmp_path / "dyn", n_train=2, n_val=4, size=(32, 32))
    run = tmp_path / "run"
    ckpt = write_checkpoint(run, root, phase=2)
    task, task_cfg, stored = load_task(ckpt)
    data_cfg = data_config(stored.dataset)
    protocol = build_reader(data_cfg).place_protocol(data_cfg.split)
    first = evaluate_retrieval(task, protocol, task_cfg.vpr, "cpu", vpr_dir(run, data_cfg.name), model_id(ckpt),
                               data_cfg.val_batch_size)["metrics"]
    return root, run, ckpt, first


def test_an_evaluation_reuses_the_training_runs_artefacts_read_only(trained, tmp_path):
    root, run, ckpt, first = trained
    records = snapshot(run / "vpr")
    assert {"vocabulary.npz", "gallery_val_predicted.npz", "metrics_val.json"} <= {p.name for p in records}
    again = evaluate(evaluation(root, tmp_path / "again"), ckpt)
    assert {k: v for k, v in again.items() if "R@" in k} == {k: v for k, v in first.items() if "R@" in k}
    # the vocabulary and gallery came from the training run: only the metrics are written, in the evaluation's dir
    assert sorted(p.name for p in (tmp_path / "again" / "vpr").iterdir()) == ["metrics_val.json"]
    assert snapshot(run / "vpr") == records


def test_another_data_root_writes_only_to_the_evaluations_dir(trained, tmp_path):
    _, run, ckpt, _ = trained
    records = snapshot(run / "vpr")
    other = write_tiny_dynamic(tmp_path / "other", n_train=2, n_val=4, size=(32, 32), seed=1)
    evaluate(evaluation(other, tmp_path / "other_eval"), ckpt)
    written = {p.name for p in (tmp_path / "other_eval" / "vpr").iterdir()}
    assert {"vocabulary.npz", "gallery_val_predicted.npz", "metrics_val.json"} <= written
    assert snapshot(run / "vpr") == records  # the run's metrics_val.json, vocabulary and gallery are its own


def test_a_copied_checkpoint_gets_nothing_written_beside_it(trained, tmp_path):
    root, _, ckpt, _ = trained
    copy = tmp_path / "copies" / "best.pt"
    copy.parent.mkdir()
    shutil.copy(ckpt, copy)
    evaluate(evaluation(root), copy)  # no run dir: the artefacts live in a temporary folder, removed after
    assert [p.name for p in (tmp_path / "copies").iterdir()] == ["best.pt"] and not (tmp_path / "vpr").exists()
    evaluate(evaluation(root, tmp_path / "named"), copy)
    assert (tmp_path / "named" / "vpr" / "metrics_val.json").is_file()
    with pytest.raises(ConfigError, match="is the training run of"):
        evaluate(evaluation(root, trained[1]), ckpt)


def test_a_phase1_checkpoint_prints_its_table(tmp_path, capsys, one_thread):
    root = write_tiny_dynamic(tmp_path / "dyn", n_train=2, n_val=2, size=(32, 32))
    ckpt = write_checkpoint(tmp_path / "run", root, phase=1)
    scores = evaluate(evaluation(root, tmp_path / "eval"), ckpt)
    printed = capsys.readouterr().out
    assert "| PA | MPA | MIoU | FWIoU |" in printed
    assert f"| {scores['PA']:.4f} | {scores['MPA']:.4f} | {scores['MIoU']:.4f} | {scores['FWIoU']:.4f} |" in printed
    for c, name in enumerate(STATIC_CLASSES):
        assert (f"| {name} | {scores[f'IoU_{c}']:.4f} |" in printed) == (f"IoU_{c}" in scores)
    assert any(f"IoU_{c}" in scores for c in range(NUM_CLASSES))
