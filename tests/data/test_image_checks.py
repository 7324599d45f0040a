"""Images are fully decoded or rejected: the start-up check names each kind of broken file, remembers what passed,
and the training-time read refuses a truncated image naming it (geoloc.data.validate)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from geoloc.data import validate
from geoloc.data.validate import DatasetFileError, check_files, image_problem
from geoloc.tasks.crossview.data_config import CrossViewDataConfig

from conftest import REALDATA
from helpers.crossview_runs import pairs_of


def write_images(folder, n=6, size=(40, 56)):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        path = folder / f"{i:03d}.{'jpg' if i % 2 == 0 else 'png'}"
        cv2.imwrite(str(path), rng.integers(0, 255, (*size, 3), np.uint8))
        paths.append(path)
    return paths


def cut(path, keep):
    path.write_bytes(path.read_bytes()[:keep])


@pytest.fixture
def images(tmp_path):
    return write_images(tmp_path / "img")


def test_complete_images_pass(images):
    assert [image_problem(p) for p in images] == [None] * len(images)
    check_files(images, images[0].parent, "train")


def test_each_kind_of_broken_file_is_named(images, tmp_path):
    jpg, png = images[0], images[1]
    cut(jpg, len(jpg.read_bytes()) // 2)  # a partial download: libjpeg alone would fill it with grey
    cut(png, -20)
    assert cv2.imread(str(jpg)) is not None  # the decoder itself does not refuse it
    images[2].write_bytes(b"")
    images[3].write_bytes(b"<!DOCTYPE html><title>404</title>")  # an error page saved as an image
    data = bytearray(images[4].read_bytes())
    mid = len(data) // 2
    data[mid:mid + 2] = b"\xff\xd9"  # an end marker inside the scan: libjpeg's "premature end of data segment"
    images[4].write_bytes(bytes(data))
    images[5].unlink()
    with pytest.raises(DatasetFileError) as err:
        check_files(images, tmp_path / "img", "val", show=6)
    text = str(err.value)
    assert f"6 of 6 files of split 'val' under root {tmp_path / 'img'}" in text
    for path, why in [(jpg, "truncated JPEG: premature end, no end-of-image marker FF D9"),
                      (png, "truncated PNG: no IEND chunk"), (images[2], "zero bytes"),
                      (images[3], "not an image: does not decode, and it starts with b'<!DOCTYPE html><'"),
                      (images[4], f"premature end of JPEG data: an end-of-image marker at byte {mid} of"),
                      (images[5], "missing")]:
        assert f"{path} ({why}" in text, why


def test_padding_after_the_end_marker_is_accepted(images):
    for p in images[:2]:
        p.write_bytes(p.read_bytes() + b"\x00" * 16)
        assert image_problem(p) is None


def count_decodes(monkeypatch):
    """The shapes of the images decoded from now on."""
    shapes = []

    def counted(data):
        img, problem = real(data)
        if img is not None:
            shapes.append(img.shape)
        return img, problem

    real = validate._decoded
    monkeypatch.setattr(validate, "_decoded", counted)
    return shapes


def test_passed_files_are_remembered_by_size_and_mtime(images, monkeypatch, checked_files_cache):
    root = images[0].parent
    decodes = count_decodes(monkeypatch)
    check_files(images, root, "train")
    assert decodes == [(40, 56, 3)] * 6  # every image, at full size
    check_files(images, root, "train")
    assert len(decodes) == 6  # the second start decodes nothing
    cache = json.loads(validate.cache_file(root, "train", "decode").read_text())
    assert validate.cache_file(root, "train", "decode").parent == checked_files_cache  # not in the dataset
    assert sorted(cache["files"]) == sorted(map(str, images))
    original = images[0].read_bytes()
    cut(images[0], -2)  # changed since: checked again, and caught
    with pytest.raises(DatasetFileError, match="000.jpg \\(truncated JPEG"):
        check_files(images, root, "train")
    assert len(decodes) == 6  # the tail alone condemned it, before any decode
    images[0].write_bytes(original)  # repaired: decoded once more, then remembered again
    check_files(images, root, "train")
    assert len(decodes) == 7
    check_files(images, root, "val")  # another split has its own record
    assert len(decodes) == 13


def test_unwritable_cache_only_costs_a_recheck(images, monkeypatch, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setattr(validate, "checked_dir", lambda: blocker / "checked")  # mkdir fails under a file
    decodes = count_decodes(monkeypatch)
    check_files(images, images[0].parent, "train")
    check_files(images, images[0].parent, "train")
    assert len(decodes) == 12


def test_a_truncated_image_at_training_time_names_the_file(tiny_cvusa):
    cfg = CrossViewDataConfig(name="cvusa", root=str(tiny_cvusa), aerial_size=32, pano_size=[16, 64],
                              check_files="exists")
    ds = pairs_of(cfg, "train", train=True)
    aerial = tiny_cvusa / "bingmap/19/0000003.jpg"
    cut(aerial, len(aerial.read_bytes()) - 300)
    with pytest.raises(DatasetFileError, match=r"0000003.jpg: truncated JPEG: premature end"):
        ds[(2, 0)]
    aerial.write_bytes(b"")
    with pytest.raises(DatasetFileError, match=r"0000003.jpg: zero bytes"):
        ds[(2, 0)]


@pytest.mark.skipif(not REALDATA.is_dir(), reason="real sample imagery not present")
def test_real_dataset_images_pass():
    files = sorted(REALDATA.rglob("*.jpg")) + sorted(REALDATA.rglob("*.png"))
    assert files and [(f, image_problem(f)) for f in files] == [(f, None) for f in files]


def cut_mid_scan(path) -> None:
    """Cut a JPEG in the middle of its scan and append an end marker: every byte-level check passes (the first
    FF D9 after the scan is the last), and libjpeg alone decodes it with the rest of the image grey."""
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2] + b"\xff\xd9")


def header_promises_more(path, height=4999, width=5000) -> None:
    """A small JPEG whose frame header claims height x width: libjpeg alone returns a grey picture of that size."""
    data = bytearray(path.read_bytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 7] = height.to_bytes(2, "big")
    data[sof + 7:sof + 9] = width.to_bytes(2, "big")
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", [cut_mid_scan, header_promises_more])
def test_a_jpeg_that_only_looks_complete_is_refused_at_start_up_and_when_read(images, tmp_path, damage):
    jpg = images[0]
    damage(jpg)
    data = jpg.read_bytes()
    assert validate.content_problem(data) is None  # the byte-level checks alone let it through
    assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) is not None  # OpenCV fills it with grey
    with pytest.raises(DatasetFileError, match=rf"{jpg} \(corrupt JPEG: Corrupt JPEG data: premature end"):
        check_files(images, tmp_path / "img", "val")
    from geoloc.data.io import read_rgb

    with pytest.raises(DatasetFileError, match=rf"{jpg}: corrupt JPEG: .*premature end"):
        read_rgb(jpg)


def test_the_strict_decoder_gives_opencvs_pixels(images):
    """Decoding through libjpeg-turbo's strict mode changes no pixel of a complete JPEG (the figures stay)."""
    from geoloc.data.io import read_rgb

    for path in images + sorted(REALDATA.glob("*/*/*/*.jpg"))[:4]:
        expected = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        assert np.array_equal(read_rgb(path), expected), path
