"""The dynamic-scene place protocol on the released formats: the authors' 4-panel CARLA PNGs and the Empty Cities
3-panel images, made from a tiny synthetic `dynamic` layout by data_prep/dynamic_to_panels.py. The dynamic view
of each file is a query, and the static view of the same file is its positive in the gallery."""

import dataclasses
import importlib.util
import json

import pytest
import torch
from geoloc.config import ConfigError
from geoloc.launch import run
from geoloc.tasks import mmdip
from geoloc.tasks.mmdip.datasets import (
    CarlaFourPanelDataset,
    DynamicDataset,
    EmptyCitiesDataset,
)
from geoloc.tasks.mmdip.pipeline import load_task
from geoloc.tasks.mmdip.mmdip_config import DynamicDataConfig
from geoloc.tasks.mmdip.protocol import FROM_GALLERY, FROM_TRAIN
from geoloc.tasks.mmdip.readers import build_reader
from geoloc.tasks.mmdip.retrieval import evaluate_retrieval

from conftest import REPO, compose_evaluate, compose_train
from helpers.dynamic_data import TINY_MMDIP, evaluate, write_tiny_dynamic

def place_protocol(name, root, split, image_size):
    """The place protocol of the reader `name` registers, on `split` of `root`."""
    return build_reader(DynamicDataConfig(name=name, root=str(root), image_size=list(image_size))).place_protocol(split)


_spec = importlib.util.spec_from_file_location("dynamic_to_panels", REPO / "data_prep" / "dynamic_to_panels.py")
to_panels = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(to_panels)

N_TRAIN, N_VAL = 4, 6  # 6 places: R@5 is not 1 by construction
RECALL_KEYS = ("R@1", "R@5", "R@10", "R@1%")
IMAGE_KEYS = ("L1", "L2", "PSNR", "SSIM")


def test_panels_read_back_as_the_dynamic_layout(tmp_path):
    root = write_tiny_dynamic(tmp_path / "dyn", n_train=2, n_val=3)
    for fmt in ("carla4", "emptycities"):
        counts = to_panels.convert(root, tmp_path / fmt, fmt)
        assert counts == {"train": 4, "val": 3}  # train: both views of each place; val: the query view only
    source = DynamicDataset(root, "val", roles=("query",))
    carla = CarlaFourPanelDataset(tmp_path / "carla4", "val")
    empty = EmptyCitiesDataset(tmp_path / "emptycities", "val")
    for i in range(len(source)):
        want = source[i]
        for got in (carla[i], empty[i]):
            for key in ("dynamic", "static", "mask"):
                assert torch.equal(got[key], want[key]), key
        assert torch.equal(carla[i]["label"], want["label"])  # static classes -> CARLA tags -> static classes
    assert json.loads((tmp_path / "carla4/class_fractions.json").read_text()) == json.loads(
        (root / "class_fractions.json").read_text())


def test_place_protocol_pairs_each_dynamic_view_with_the_static_view_of_its_place(tmp_path):
    root = write_tiny_dynamic(tmp_path / "dyn", n_train=2, n_val=3)
    for fmt in ("carla4", "emptycities"):
        to_panels.convert(root, tmp_path / fmt, fmt)
        protocol = place_protocol(fmt, tmp_path / fmt, "val", (64, 64))
        assert len(protocol.queries) == len(protocol.references) == 3
        assert protocol.vocabulary_source == FROM_TRAIN and len(protocol.vocabulary) == 4
        assert protocol.has_labels == (fmt == "carla4")  # what vpr.gallery_seg=label needs
        refs = {int(r["place"]): r for r in protocol.references}
        for q in protocol.queries:
            ref = refs[int(q["place"])]
            assert torch.equal(ref["static"], q["static"]) and not torch.equal(q["dynamic"], q["static"])
    # no train/ folder beside the images: the vocabulary comes from the gallery, and says so
    flat = place_protocol("emptycities", tmp_path / "emptycities" / "val", None, (64, 64))
    assert flat.vocabulary_source == FROM_GALLERY and len(flat.queries) == 3
    # the synthetic layout: queries are the query rows, their positives the reference rows of the same place
    dyn = place_protocol("dynamic", root, "val", (64, 64))
    assert sorted(int(r["place"]) for r in dyn.references) == sorted(int(q["place"]) for q in dyn.queries)
    assert all(bool(q["is_query"]) for q in dyn.queries) and not any(bool(r["is_query"]) for r in dyn.references)
    with pytest.raises(ConfigError, match=r"dataset.name='cvusa' is not a known mmdip_dataset; choose one of "
                                          r"\['carla4', 'dynamic', 'emptycities'"):
        place_protocol("cvusa", root, "val", (64, 64))


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """One tiny trained MMDIP run (1 + 1 epochs on the synthetic layout) and its data, shared by this file."""
    tmp = tmp_path_factory.mktemp("mmdip_realformat")
    root = write_tiny_dynamic(tmp / "dyn", n_train=N_TRAIN, n_val=N_VAL)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        mmdip.train(compose_train([*TINY_MMDIP, f"dataset.root={root}", f"run_dir={tmp / 'run'}"]), tmp / "run")
    finally:
        torch.set_num_threads(threads)
    return tmp, root, tmp / "run" / "phase2" / "best.pt"


@pytest.mark.slow
def test_evaluate_reports_the_place_protocol_on_both_panel_formats(tiny_run, one_thread):
    tmp, root, ckpt = tiny_run
    own_gallery = ckpt.parent.parent / "vpr" / "gallery_val_predicted.npz"  # coded at the end of training
    own_mtime, results = own_gallery.stat().st_mtime_ns, {}
    for fmt in ("carla4", "emptycities"):
        to_panels.convert(root, tmp / fmt, fmt)
        out = tmp / f"{fmt}.json"
        run.evaluate(compose_evaluate([f"ckpt={ckpt}", f"dataset={fmt}", f"dataset.root={tmp / fmt}",
                                       "dataset.split=val", f"metrics_out={out}", "device=cpu",
                                       f"run_dir={tmp / f'evaluate_{fmt}'}"]))
        m = results[fmt] = json.loads(out.read_text())
        assert set(RECALL_KEYS) | set(IMAGE_KEYS) | {"num_queries", "num_images"} <= set(m)
        assert m["num_queries"] == m["num_images"] == N_VAL
        assert all(0 <= m[k] <= 1 for k in RECALL_KEYS) and 0 <= m["SSIM"] <= 1 and m["PSNR"] > 0
        assert m["vocabulary_source"] == FROM_TRAIN and m["gallery_seg"] == "predicted"
        # the pairing, checked without the model: a raw dynamic view differs from its static view by two cars,
        # so ORB words alone find it; a query paired with another place's static view would score near 1/6
        assert m["dynamic-BoW/R@1"] >= 0.8
        # the evaluation's artefacts are in its own run dir, none in the training run
        assert (tmp / f"evaluate_{fmt}" / "vpr" / fmt / "gallery_val_predicted.npz").is_file()
        assert not (ckpt.parent.parent / "vpr" / fmt).exists()
    # the same places through the two readers: the same images, the same numbers
    for key in (*RECALL_KEYS, *IMAGE_KEYS, "BoW/R@1", "SPM/R@1"):
        assert results["carla4"][key] == pytest.approx(results["emptycities"][key], abs=1e-9), key
    # evaluating the panel data left the run's own (synthetic layout) artefacts alone
    assert own_gallery.stat().st_mtime_ns == own_mtime


@pytest.mark.slow
def test_gallery_from_labels_where_the_reader_has_them(tiny_run, one_thread, tmp_path):
    tmp, root, ckpt = tiny_run
    task, task_cfg, _ = load_task(ckpt)
    wants_labels = dataclasses.replace(task_cfg.vpr, gallery_seg="label")
    for fmt, used in (("carla4", "label"), ("emptycities", "predicted")):
        to_panels.convert(root, tmp_path / fmt, fmt)
        protocol = place_protocol(fmt, tmp_path / fmt, "val", (64, 64))
        said = []
        m = evaluate_retrieval(task, protocol, wants_labels, "cpu", tmp_path / f"vpr_{fmt}", "tiny", 4,
                               log=said.append)["metrics"]
        assert m["gallery_seg"] == used and (tmp_path / f"vpr_{fmt}" / f"gallery_val_{used}.npz").is_file()
        assert any("has no segmentation labels" in line for line in said) == (fmt == "emptycities")
    phase1 = ckpt.parent.parent / "phase1" / "best.pt"
    cfg = compose_evaluate([f"ckpt={phase1}", "dataset=emptycities", f"dataset.root={tmp_path / 'emptycities'}"])
    with pytest.raises(ConfigError, match="phase-1 .* dataset=emptycities has none"):
        evaluate(cfg, phase1)
