"""export.py format=onnx: the two encoders run in onnxruntime at any batch size and give torch's descriptors; the
JSON's shapes are the ones the files take; existing files, other formats, other tasks and opsets torch does not
write are refused, and the opset asked for is the one written."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from geoloc.apps.export.onnx_export import export
from geoloc.config import ConfigError, to_yaml
from geoloc.engine import checkpoint as ckpt_io
from hydra import compose, initialize_config_dir

from conftest import CONF, TINY, compose_train
from helpers.crossview_runs import task_of

ort = pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxscript")


def compose_export(overrides: list[str]):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("export", overrides=overrides)


def write_checkpoint(path, overrides: list[str], views: dict | None = None):
    """A checkpoint as the trainer writes it (the task's weights, the resolved config and the query views of the
    splits it saw, by default CVUSA's), untrained: export needs no data, and any weights test the graph as well as
    trained ones."""
    cfg = compose_train([*TINY, *overrides, f"run_dir={path.parent}"])
    torch.manual_seed(0)
    task = task_of(cfg)
    task.query_views = views if views is not None else {"train": "panorama", "val": "panorama"}
    ckpt_io.save_atomic({"task": task.state_dict(), "config": to_yaml(cfg), "epoch": 0,
                         "task_info": task.checkpoint_info()}, path)
    return task


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """(torch task, out dir, spec) of the TINY model (VGG16-BN + MSAE) under alignment=polar (both branches take
    the 16x64 panorama shape) exported once, with the default out, over a stale encoders.json (overwrite=true).
    One export for the whole module: each costs seconds."""
    base = tmp_path_factory.mktemp("export")
    task = write_checkpoint(base / "best.pt", ["dataset.alignment=polar"])
    (base / "best_onnx").mkdir()
    (base / "best_onnx" / "encoders.json").write_text("stale")
    spec = export(compose_export([f"ckpt={base / 'best.pt'}", "overwrite=true"]))
    return task.eval(), base / "best_onnx", spec


def run_both(module, session, shape, batch):
    x = torch.randn(batch, *shape, generator=torch.Generator().manual_seed(batch))
    with torch.no_grad():
        expected = module(x).numpy()
    got = session.run(None, {session.get_inputs()[0].name: x.numpy()})[0]
    return got, expected


@pytest.mark.slow
@pytest.mark.parametrize("branch", ["query", "reference"])
def test_onnx_encoders_match_torch_at_two_batch_sizes(exported, branch):
    task, out, spec = exported
    entry = spec[branch]
    session = ort.InferenceSession(str(out / entry["file"]), providers=["CPUExecutionProvider"])
    assert session.get_inputs()[0].name == entry["input"]["name"] == "image"
    shape = entry["input"]["shape"][1:]
    assert shape == [3, 16, 64]  # polar: both branches take pano_size (H, W), and the file takes exactly that
    module = getattr(task.model, branch)
    for batch in (1, 5):  # the export's example batch was 2: other sizes prove the batch is dynamic
        got, expected = run_both(module, session, shape, batch)
        assert got.shape == (batch, entry["output"]["shape"][1]) == (batch, 16)
        assert np.abs(got - expected).max() < 1e-4
        assert np.allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)  # the JSON says l2_normalised
    assert entry["output"]["l2_normalised"] is True
    assert entry["checked_against_torch"]["max_abs_diff"] < 1e-4


@pytest.mark.slow
def test_spec_is_written_and_records_the_preprocessing(exported):
    _, out, spec = exported
    assert sorted(p.name for p in out.iterdir()) == ["encoders.json", "query.onnx", "reference.onnx"]
    assert json.loads((out / "encoders.json").read_text()) == spec  # the stale file was replaced (overwrite=true)
    assert spec["dataset"] == {"name": "cvusa", "alignment": "polar", "aerial_size": 32, "pano_size": [16, 64]}
    assert spec["normalisation"]["channel_order"] == "RGB"
    assert spec["normalisation"]["mean"] == pytest.approx([0.485, 0.456, 0.406])
    assert spec["normalisation"]["std"] == pytest.approx([0.229, 0.224, 0.225])
    assert any("aerial_to_polar" in step for step in spec["reference"]["preprocessing"]["steps"])
    assert spec["source"]["ckpt"].endswith("best.pt")


@pytest.mark.slow
def test_existing_files_are_refused_unless_overwrite(exported):
    _, out, _ = exported
    ckpt = out.parent / "best.pt"
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    with pytest.raises(ConfigError, match=r"already holds query.onnx, reference.onnx, encoders.json.*overwrite=true"):
        export(compose_export([f"ckpt={ckpt}"]))
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before


@pytest.mark.slow
def test_the_spec_describes_the_recorded_query_view_and_where_queries_go(tmp_path):
    """University-1652 satellite -> drone: the checkpoint records drone photos ("image") for the query branch and
    aerial queries for its validation split, so query.onnx is described as taking photos, and the spec says the
    queries go through reference.onnx (against a gallery of photos through query.onnx)."""
    from geoloc.apps.export.onnx_export import export_encoders
    from geoloc.tasks.crossview import CrossViewEncoder

    write_checkpoint(tmp_path / "best.pt", ["dataset.alignment=none"], views={"train": "image", "val": "aerial"})
    encoder = CrossViewEncoder.load(tmp_path / "best.pt")
    spec = export_encoders(encoder, tmp_path / "onnx")
    assert spec["query"]["view"] == "ground (image)" and spec["query"]["input"]["shape"] == ["batch", 3, 32, 32]
    assert spec["queries"] == {"view": "aerial", "file": "reference.onnx",
                               "gallery": {"view": "image", "file": "query.onnx"}}
    assert "resize to 32x32 (cv2.INTER_AREA)" in spec["query"]["preprocessing"]["steps"]


def test_other_formats_are_refused(tmp_path):
    with pytest.raises(ConfigError, match=r"format=torchscript is not supported.*format=onnx"):
        export(compose_export([f"ckpt={tmp_path / 'none.pt'}", "format=torchscript"]))


def test_mmdip_checkpoints_are_refused(tmp_path):
    cfg = compose_train(["task=mmdip", f"run_dir={tmp_path}"])
    ckpt_io.save_atomic({"task": {}, "config": to_yaml(cfg)}, tmp_path / "best.pt")
    with pytest.raises(ConfigError, match=r"task=mmdip checkpoint.*cross-view"):
        export(compose_export([f"ckpt={tmp_path / 'best.pt'}", f"out={tmp_path / 'onnx'}"]))
    assert not (tmp_path / "onnx").exists()


@pytest.mark.slow
def test_a_failed_export_leaves_no_partial_file(tmp_path, monkeypatch):
    """The files are written to a temp folder and moved in at the end: the reference branch failing after the
    query branch was written leaves neither (nor the out folder the export created)."""
    from geoloc.apps.export import onnx_export

    write_checkpoint(tmp_path / "best.pt", [])
    calls = []

    def failing_second_branch(branch, example, path, opset):
        calls.append(path.name)
        if len(calls) == 2:
            raise RuntimeError("the exporter failed")
        path.write_bytes(b"a written query.onnx")
        return 20

    monkeypatch.setattr(onnx_export, "export_branch", failing_second_branch)
    monkeypatch.setattr(onnx_export, "checked", lambda *args: None)
    with pytest.raises(RuntimeError, match="the exporter failed"):
        export(compose_export([f"ckpt={tmp_path / 'best.pt'}"]))
    assert calls == ["query.onnx", "reference.onnx"]
    assert not (tmp_path / "best_onnx").exists()


@pytest.mark.parametrize("opset", ["1", "17", "99", "abc", "18.5"])
def test_an_opset_torch_does_not_write_is_refused_before_anything(tmp_path, opset):
    """torch.onnx writes opsets from torchlib's to its newest; asked for another, it printed onnx's converter
    traceback and wrote its own opset. The range comes from the installed torch, and the error names it."""
    from geoloc.apps.export.onnx_export import supported_opsets

    span = supported_opsets()
    assert span is not None and span.start <= 20 < span.stop  # torch 2.14: 18..23, default 20
    with pytest.raises(ConfigError, match=rf"opset='?{opset}'? .*{span.start}\.\.{span.stop - 1} \(torch "):
        export(compose_export([f"ckpt={tmp_path / 'none.pt'}", f"opset={opset}", f"out={tmp_path / 'onnx'}"]))
    assert not (tmp_path / "onnx").exists()


@pytest.mark.slow
def test_the_opset_asked_for_is_the_one_written(tmp_path):
    from geoloc.apps.export.onnx_export import supported_opsets

    newest = supported_opsets()[-1]
    write_checkpoint(tmp_path / "best.pt", ["dataset.alignment=polar"])
    spec = export(compose_export([f"ckpt={tmp_path / 'best.pt'}", f"opset={newest}", f"out={tmp_path / 'onnx'}"]))
    assert spec["opset"] == newest
    for name in ("query.onnx", "reference.onnx"):
        model = onnx.load(str(tmp_path / "onnx" / name))
        assert {o.domain: o.version for o in model.opset_import}[""] == newest


@pytest.mark.slow
def test_a_file_written_at_another_opset_is_refused(tmp_path, monkeypatch):
    """Should the exporter keep its own opset (as its version converter does when it fails), nothing is kept."""
    from geoloc.apps.export import onnx_export

    write_checkpoint(tmp_path / "best.pt", [])

    def keeps_its_own(branch, example, path, opset):
        path.write_bytes(b"an opset-18 file")
        return 18

    monkeypatch.setattr(onnx_export, "export_branch", keeps_its_own)
    monkeypatch.setattr(onnx_export, "checked", lambda *args: None)
    with pytest.raises(RuntimeError, match=r"query.onnx: torch.onnx wrote opset 18, not the opset=21 asked for"):
        export(compose_export([f"ckpt={tmp_path / 'best.pt'}", "opset=21", f"out={tmp_path / 'onnx'}"]))
    assert not (tmp_path / "onnx").exists()


@pytest.mark.slow
@pytest.mark.parametrize("margin", [0.0, 0.25])
def test_the_refiner_encoders_are_exported_and_match_torch(tmp_path, margin):
    """A checkpoint with a refiner adds its two encoders (refine_query.onnx, refine_reference.onnx), which give
    torch's feature maps at two batch sizes, and describes the matching in encoders.json; a refiner that reads its
    tile with a margin (refiner.margin) takes the wider tile and its coverage channel."""
    task = write_checkpoint(tmp_path / "best.pt", ["refiner=correlation", "refiner.channels=4", "refiner.width=4",
                                                   f"refiner.margin={margin}"]).eval()
    spec = export(compose_export([f"ckpt={tmp_path / 'best.pt'}"]))
    entry = spec["refiner"]
    assert entry["name"] == "correlation" and entry["side"] == 32 and "matching" in entry
    wide = 48 if margin else 32
    assert entry["reference"]["input"]["shape"] == ["batch", 4 if margin else 3, wide, wide]
    assert ("margin" in entry) == bool(margin)
    for side, encode, shape in (("query", task.refiner.encode_query, (3, 32, 32)),
                                ("reference", task.refiner.encode_reference, (4 if margin else 3, wide, wide))):
        session = ort.InferenceSession(str(tmp_path / "best_onnx" / entry[side]["file"]),
                                       providers=["CPUExecutionProvider"])
        for batch in (1, 3):
            got, expected = run_both(encode, session, shape, batch)
            assert got.shape == (batch, 4, shape[-1] // 2, shape[-1] // 2)
            assert np.abs(got - expected).max() < 1e-4
            if len(shape) == 3 and shape[0] == 4:  # cells with some pixel not covered (channel 4 <= 0.5) are zero
                assert (np.abs(got).sum(1) == 0).any() and (np.abs(got).sum(1) > 0).any()
        assert entry[side]["checked_against_torch"]["max_abs_diff"] < 1e-4
