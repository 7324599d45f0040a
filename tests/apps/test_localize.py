"""localize: positions read from the datasets, a saved gallery's places, and one image in -> the top-k with
positions, heading and truth, checked against brute-force scoring of the same descriptors."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
import torch
from geoloc.apps.localize import Localizer, read_street
from geoloc.config import ConfigError
from geoloc.datasets.cvact import cvact
from geoloc.datasets.cvusa import cvusa
from geoloc.data.positions import positions_text, read_positions
from geoloc.launch import run
from geoloc.synthetic import generate
from geoloc.synthetic.layouts import place_utm
from geoloc.tasks.crossview.datasets import CrossViewPairs
from geoloc.tasks.crossview.heading import query_candidates
from geoloc.tasks.crossview.transforms import align_query, normalise, to_tensor
from geoloc.tasks.crossview.views import view_canvas
from hydra import compose, initialize_config_dir

from conftest import CONF, REALDATA, TINY, compose_evaluate, compose_train, write_cvusa


def write_xy_positions(root, n):
    rows = [(f"streetview/panos/{i + 1:07d}.jpg", 1000.0 * i, -50.0 * i) for i in range(n)]
    (root / "positions.csv").write_text(positions_text(rows, "xy"))
    return {r[0]: r[1:] for r in rows}


@pytest.fixture(scope="module")
def gallery(tmp_path_factory):
    """(dataset root, checkpoint, gallery folder) of a 1-epoch TINY run on 12 + 8 pairs with positions.csv."""
    base = tmp_path_factory.mktemp("localize")
    root = write_cvusa(base / "cvusa", n_train=12, n_val=8)
    write_xy_positions(root, 20)
    run.train(compose_train([*TINY, f"dataset.root={root}", f"run_dir={base / 'run'}", "trainer.max_epochs=1"]))
    ckpt, folder = base / "run" / "best.pt", base / "gallery"
    run.evaluate(compose_evaluate([f"ckpt={ckpt}", "progress=false", "device=cpu", f"run_dir={base / 'eval'}",
                                   f"gallery.save={folder}"]))
    return root, ckpt, folder


def test_positions_csv_is_read_in_split_order_with_clear_errors(tmp_path):
    root = write_cvusa(tmp_path / "cvusa", n_train=3, n_val=2)
    assert cvusa(str(root), "val").query_xy is None  # no file: no positions (CVUSA's release has none)
    table = write_xy_positions(root, 5)
    split = cvusa(str(root), "val")
    expect = np.array([table[p.relative_to(root).as_posix()] for p in split.queries])
    assert np.array_equal(split.query_xy, expect) and np.array_equal(split.reference_xy, expect)
    assert split.query_latlon is None
    (root / "positions.csv").write_text("panorama,lat,lon\n" + "".join(
        f"streetview/panos/{i + 1:07d}.jpg,{40 + i},{-80 - i}\n" for i in range(5)))
    assert cvusa(str(root), "train").query_latlon.tolist() == [[40, -80], [41, -81], [42, -82]]
    (root / "positions.csv").write_text("panorama,lat,lon\nstreetview/panos/0000001.jpg,40,-80\n")
    with pytest.raises(ValueError, match="no row for streetview/panos/0000002.jpg"):
        cvusa(str(root), "train")
    (root / "positions.csv").write_text("pano,x,y\n")
    with pytest.raises(ValueError, match="first line must be one of"):
        read_positions(root, [])


def test_synthetic_layouts_write_positions_the_readers_return(tmp_path):
    """cvusa: positions.csv; cvact: ACT_data.mat's utm. Both the made-up UTM of each place number."""
    c = generate("cvusa", tmp_path / "u", train=2, val=2, seed=1, preset="tiny", progress=False)
    a = generate("cvact", tmp_path / "a", train=2, val=2, seed=1, preset="tiny", progress=False)
    for split in (cvusa(str(c), "val"), cvact(str(a), "val")):
        assert split.query_xy.tolist() == [list(place_utm(3)), list(place_utm(4))]
        assert np.array_equal(split.query_xy, split.reference_xy)
    (c / "positions.csv").unlink()  # a dataset rendered before positions existed gets them on its next use
    assert generate("cvusa", c, train=2, val=2, seed=1, preset="tiny", progress=False) == c
    assert (c / "positions.csv").is_file()


def brute_force(localizer, inputs, headings):
    """Every gallery row's best score over the candidate inputs, one forward pass each (no batching)."""
    reference = localizer.index._descriptors
    if inputs.dtype == torch.uint8:  # the data module's images, normalised on the device in training
        inputs = normalise(inputs)
    with torch.no_grad():
        scores = torch.stack([localizer.encoder.encode_street(x[None])[0] @ reference.t() for x in inputs])  # K x N
    best, k = scores.max(dim=0)
    order = sorted(range(len(best)), key=lambda r: (-float(best[r]), r))
    return [(r, float(best[r]), float(headings[int(k[r])])) for r in order]


@pytest.mark.slow
def test_localize_equals_brute_force_scoring_with_and_without_heading_search(gallery):
    root, ckpt, folder = gallery
    loc = Localizer.load(ckpt, folder, device="cpu", heading_steps=8)
    pairs = CrossViewPairs(cvusa(str(root), "val"), loc.encoder.data, train=False)
    i = 3
    path = pairs.split.queries[i]
    image = read_street(path)

    known = loc.localize(image, topk=4, heading=0, path=path).to_json()
    expect = brute_force(loc, pairs[i]["query"][None], np.array([0.0]))  # the evaluation's own query input
    assert [h["row"] for h in known["topk"]] == [r for r, _, _ in expect[:4]]
    assert [h["score"] for h in known["topk"]] == pytest.approx([s for _, s, _ in expect[:4]], abs=1e-5)

    searched = loc.localize(image, topk=5, heading="search", path=path).to_json()
    inputs, headings = query_candidates(image, loc.encoder.data, "panorama", 360.0, 8)
    expect = brute_force(loc, inputs, headings)[:5]
    assert [(h["row"], h["heading_deg"]) for h in searched["topk"]] == [(r, hd) for r, _, hd in expect]
    assert searched["heading_deg"] == expect[0][2]

    truth = searched["truth"]
    assert truth["row"] == i and truth["position"] == {"x_m": 1000.0 * (12 + i), "y_m": -50.0 * (12 + i)}
    top1 = searched["topk"][0]
    assert truth["error_m"] == pytest.approx(np.hypot(top1["x_m"] - 1000.0 * (12 + i), top1["y_m"] + 50.0 * (12 + i)))
    assert truth["rank"] == next((h["rank"] for h in searched["topk"] if h["row"] == i), None)
    assert json.loads(json.dumps(searched)) == searched  # JSON as it is


@pytest.mark.slow
def test_a_limited_fov_photo_is_placed_on_the_canvas(gallery):
    root, ckpt, folder = gallery
    loc = Localizer.load(ckpt, folder, device="cpu")
    image = read_street(root / "streetview/panos/0000013.jpg")
    photo = image[:, 10:42]  # 32 of 64 columns: a 180° view
    answer = loc.localize(photo, fov=180.0, topk=2, heading=90.0).to_json()
    x = to_tensor(align_query(view_canvas(photo, 180.0, 90.0), loc.encoder.data, "panorama"))
    assert answer["topk"][0]["row"] == brute_force(loc, x[None], np.array([90.0]))[0][0]
    assert answer["heading_deg"] == 90.0 and "truth" not in answer  # no path given: the truth is not looked up


@pytest.mark.slow
def test_localize_refuses_a_gallery_of_other_weights_or_without_places(gallery, tmp_path):
    root, ckpt, folder = gallery
    other = tmp_path / "other"
    shutil.copytree(folder, other)
    info = json.loads((other / "gallery.json").read_text())
    (other / "gallery.json").write_text(json.dumps({**info, "model_fingerprint": "0" * 64}))
    with pytest.raises(ConfigError, match=f"gallery in {other} was built with other weights"):
        Localizer.load(ckpt, other)
    (other / "gallery.json").write_text(json.dumps(info))
    (other / "references.jsonl").unlink()
    with pytest.raises(FileNotFoundError, match="lacks references.jsonl.*gallery.save="):
        Localizer.load(ckpt, other)
    with pytest.raises(FileNotFoundError, match="no saved gallery.*gallery.save="):
        Localizer.load(ckpt, tmp_path / "nothing")
    loc = Localizer.load(ckpt, folder, device="cpu")
    with pytest.raises(ValueError, match="H×W×3 uint8"):
        loc.localize(np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match=r"fov=0 is outside \(0, 360\]"):
        loc.localize(np.zeros((16, 64, 3), np.uint8), fov=0)


def test_localize_py_answers_a_folder_with_one_json_line_and_picture_each(gallery, tmp_path, capsys):
    from geoloc.apps.localize.command import localize

    root, ckpt, folder = gallery
    images = tmp_path / "images"
    images.mkdir()
    for n in (13, 14):
        shutil.copy(root / f"streetview/panos/{n:07d}.jpg", images)
    (images / "notes.txt").write_text("not an image")
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("localize", overrides=[f"ckpt={ckpt}", f"gallery={folder}", f"image={images}", "topk=3",
                                             f"out={tmp_path / 'out'}", "device=cpu", "heading=search",
                                             "heading_steps=4"])
    answers = localize(cfg)
    lines = (tmp_path / "out" / "localize.jsonl").read_text().splitlines()
    assert [json.loads(line) for line in lines] == answers and len(answers) == 2
    assert capsys.readouterr().out.splitlines() == lines  # printed as written
    for n, answer in zip((13, 14), answers):
        assert answer["image"].endswith(f"{n:07d}.jpg") and len(answer["topk"]) == 3
        assert (tmp_path / "out" / f"{n:07d}.jpg.png").stat().st_size > 0
        assert "truth" not in answer  # copies outside the dataset root are not the split's queries
    (images / "0000013.jpg").unlink()
    (images / "0000014.jpg").unlink()
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("localize", overrides=[f"ckpt={ckpt}", f"gallery={folder}", f"image={images}", "out=x"])
    with pytest.raises(FileNotFoundError, match="without .jpg"):
        localize(cfg)


@pytest.mark.slow
@pytest.mark.skipif(not (REALDATA / "cvusa_mini").is_dir(), reason="../shared/realdata is absent")
def test_localize_a_real_cvusa_panorama_against_a_gallery_of_its_folder(gallery, tmp_path):
    """A real panorama against a gallery built from the same folder (2 val pairs)."""
    _, ckpt, _ = gallery
    root, folder = REALDATA / "cvusa_mini", tmp_path / "real_gallery"
    run.evaluate(compose_evaluate([f"ckpt={ckpt}", "progress=false", "device=cpu", f"run_dir={tmp_path / 'eval'}",
                                   "dataset=cvusa", f"dataset.root={root}", f"gallery.save={folder}"]))
    loc = Localizer.load(ckpt, folder, device="cpu")
    split = cvusa(str(root), "val")
    answer = loc.localize(read_street(split.queries[1]), topk=5, heading=0, path=split.queries[1]).to_json()
    assert len(answer["topk"]) == 2 and answer["truth"]["row"] == 1  # the gallery holds the 2 val tiles
    assert answer["position"] is None and "error_m" not in answer["truth"]  # CVUSA's release has no positions
    assert answer["truth"]["reference"] == "bingmap/19/0000005.jpg"


def compose_localize(*overrides):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("localize", overrides=["device=cpu", "heading=0", "topk=2", *overrides])


def test_localize_py_never_writes_among_its_inputs_and_names_each_figure(gallery, tmp_path, capsys):
    """out= pointed at the image folder used to write the figures over the inputs (a.png's figure is a.png) and
    score a figure as the next query; a.jpg and a.png wrote the same a.png."""
    from geoloc.apps.localize.command import localize

    root, ckpt, folder = gallery
    images = tmp_path / "images"
    images.mkdir()
    shutil.copy(root / "streetview/panos/0000013.jpg", images / "a.jpg")
    cv2.imwrite(str(images / "a.png"), cv2.imread(str(root / "streetview/panos/0000014.jpg")))
    before = {p.name: p.read_bytes() for p in images.iterdir()}
    for image in (images, images / "a.png"):
        with pytest.raises(ConfigError, match=f"out={images} is the folder of the input images"):
            localize(compose_localize(f"ckpt={ckpt}", f"gallery={folder}", f"image={image}", f"out={images}"))
    assert {p.name: p.read_bytes() for p in images.iterdir()} == before
    answers = localize(compose_localize(f"ckpt={ckpt}", f"gallery={folder}", f"image={images}",
                                        f"out={tmp_path / 'out'}"))
    assert [a["picture"] for a in answers] == [str(tmp_path / "out" / n) for n in ("a.jpg.png", "a.png.png")]
    assert (tmp_path / "out" / "a.jpg.png").read_bytes() != (tmp_path / "out" / "a.png.png").read_bytes()


def test_localize_py_holds_the_lock_of_its_out_folder(gallery, tmp_path):
    from geoloc.apps.localize.command import localize
    from geoloc.launch.rundir import RunDirTaken, claimed

    root, ckpt, folder = gallery
    out = tmp_path / "out"
    cfg = compose_localize(f"ckpt={ckpt}", f"gallery={folder}", f"image={root / 'streetview/panos/0000013.jpg'}",
                           f"out={out}")
    with claimed(out, role="localization", key="out"):  # another localize.py writing there now
        with pytest.raises(RunDirTaken, match=f"run dir {out} is in use by another live run .*Choose another out"):
            localize(cfg)
        assert not (out / "localize.jsonl").exists()
    assert len(localize(cfg)) == 1 and len((out / "localize.jsonl").read_text().splitlines()) == 1


@pytest.mark.slow
def test_a_gallery_saved_with_a_relative_root_keeps_the_truth_from_another_folder(gallery, tmp_path, monkeypatch):
    root, ckpt, _ = gallery
    work = tmp_path / "work"
    work.mkdir()
    shutil.copytree(root, work / "cvusa")
    monkeypatch.chdir(work)
    run.evaluate(compose_evaluate([f"ckpt={ckpt}", "progress=false", "device=cpu", f"run_dir={tmp_path / 'eval'}",
                                   "dataset.root=cvusa", f"gallery.save={tmp_path / 'g'}"]))
    assert json.loads((tmp_path / "g" / "gallery.json").read_text())["root"] == str((work / "cvusa").resolve())
    monkeypatch.chdir(tmp_path)  # localize.py run from another folder
    loc = Localizer.load(ckpt, tmp_path / "g", device="cpu")
    query = work / "cvusa" / "streetview/panos/0000014.jpg"
    answer = loc.localize(read_street(query), topk=3, heading=0, path=query).to_json()
    assert answer["truth"]["row"] == 1 and answer["truth"]["reference"] == "bingmap/19/0000014.jpg"


@pytest.mark.parametrize("damage", ["other_weights", "short_references", "calibration_targets_a_list"])
def test_geoloc_serve_refuses_a_gallery_it_cannot_trust_before_serving(gallery, tmp_path, monkeypatch, capsys,
                                                                        damage):
    """A references.jsonl shorter than the index used to pass /health, then answer 500 IndexError; a
    calibration.json whose targets are a list stopped the start with a raw AttributeError naming no file."""
    import uvicorn
    from geoloc import cli

    _, ckpt, folder = gallery
    other = tmp_path / "g"
    shutil.copytree(folder, other)
    if damage == "other_weights":
        info = json.loads((other / "gallery.json").read_text())
        (other / "gallery.json").write_text(json.dumps({**info, "model_fingerprint": "0" * 64}))
        says = f"gallery in {other} was built with other weights"
    elif damage == "calibration_targets_a_list":
        (other / "calibration.json").write_text(json.dumps({"calibrated": False, "why": "x", "targets": [1, 2]}))
        says = f'{other / "calibration.json"} holds "targets" as a JSON list'
    else:
        lines = (other / "references.jsonl").read_text().splitlines()
        (other / "references.jsonl").write_text("\n".join(lines[:-2]) + "\n")
        says = f"{other / 'references.jsonl'} holds 6 references, but the gallery has 8 rows"
    monkeypatch.setattr(uvicorn, "run", lambda *a, **k: pytest.fail("served a gallery it cannot trust"))
    assert cli.main(["serve", f"ckpt={ckpt}", f"gallery={other}", "device=cpu"]) == 2
    err = capsys.readouterr().err
    assert says in err and "gallery.save=" in err, err
