"""JPEGs decoded at reduced scale (libjpeg's DCT scaling) where the transforms resize them to no less: close to a
full decode and resize, used only where allowed, as strict as a full decode, and never by the start-up check."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import simplejpeg
import torch
from geoloc.data import validate
from geoloc.data.validate import DatasetFileError, decode_rgb, jpeg_reduction
from geoloc.datasets.cvusa import cvusa
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.datasets import CrossViewPairs, ViewImages, read_split
from geoloc.tasks.crossview.transforms import align_reference, decode_size, image_tensor

from conftest import REALDATA, write_cvusa


def smooth_jpeg(height=600, width=400) -> bytes:
    y, x = np.mgrid[0:height, 0:width]
    rgb = np.stack([128 + 100 * np.sin(x / 37.0), 128 + 100 * np.cos(y / 23.0), 128 + 60 * np.sin((x + y) / 50.0)],
                   -1).astype(np.uint8)
    return cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()


@pytest.mark.parametrize("height, width, min_size, factor", [
    (750, 750, (288, 288), 2),   # CVUSA's aerial for the paper's 288: 375 px
    (1200, 1200, (288, 288), 4),  # CVACT's: 300 px
    (750, 750, (94, 94), 8),     # ceil(750 / 8) = 94 is still enough
    (750, 750, (95, 95), 4),
    (600, 400, (76, 50), 4),     # each side must stay large enough
    (64, 64, (64, 64), 1),       # no reduction: never decoded smaller than the resize's target
    (64, 64, (100, 100), 1),     # a smaller image is upsampled as before, from its full decode
    (750, 750, None, 1),
])
def test_the_reduction_is_the_largest_that_keeps_the_target(height, width, min_size, factor):
    assert jpeg_reduction(height, width, min_size) == factor


def test_a_reduced_decode_is_a_full_decode_resized():
    data = smooth_jpeg()
    reduced = decode_rgb(data, "smooth.jpg", min_size=(70, 50))
    assert reduced.shape == (75, 50, 3)  # 1/8 scale
    resized = cv2.resize(decode_rgb(data, "smooth.jpg"), (50, 75), interpolation=cv2.INTER_AREA)
    assert np.abs(reduced.astype(int) - resized).max() <= 3
    assert decode_rgb(data, "smooth.jpg", min_size=(76, 50)).shape == (150, 100, 3)  # 1/4: 1/8 would be too small


@pytest.mark.skipif(not REALDATA.is_dir(), reason="no real CVUSA images here")
def test_real_aerials_at_half_scale_give_the_papers_input_closely():
    for path in sorted(REALDATA.glob("cvusa_mini/bingmap/19/*.jpg"))[:2]:
        data = path.read_bytes()
        reduced = decode_rgb(data, path, min_size=(288, 288))
        assert reduced.shape == (375, 375, 3)
        a = cv2.resize(reduced, (288, 288), interpolation=cv2.INTER_AREA).astype(int)
        b = cv2.resize(decode_rgb(data, path), (288, 288), interpolation=cv2.INTER_AREA).astype(int)
        assert np.abs(a - b).mean() < 3  # levels of 255: chroma upsampling and IDCT rounding differ, no more


def test_the_resize_interpolation_is_area_unless_linear_is_asked_for():
    img = cv2.resize(np.random.default_rng(0).integers(0, 256, (40, 40, 3), dtype=np.uint8), (375, 375))
    area, linear = CrossViewDataConfig(alignment="ipt", aerial_size=288), CrossViewDataConfig(
        alignment="ipt", aerial_size=288, resize_interpolation="linear")
    assert np.array_equal(align_reference(img, area), cv2.resize(img, (288, 288), interpolation=cv2.INTER_AREA))
    assert np.array_equal(align_reference(img, linear), cv2.resize(img, (288, 288), interpolation=cv2.INTER_LINEAR))
    assert not np.array_equal(align_reference(img, area), align_reference(img, linear))
    big = cv2.resize(img, (600, 600))  # a 2x reduction or more: bilinear would alias, so it is the area average
    assert np.array_equal(align_reference(big, linear), cv2.resize(big, (288, 288), interpolation=cv2.INTER_AREA))
    with pytest.raises(ValueError, match="resize_interpolation must be one of"):
        CrossViewDataConfig(resize_interpolation="cubic")


@pytest.mark.skipif(not REALDATA.is_dir(), reason="no real CVUSA images here")
def test_a_bilinear_resize_of_the_half_scale_aerial_is_as_close_to_the_papers_input_as_an_area_one():
    for path in sorted(REALDATA.glob("cvusa_mini/bingmap/19/*.jpg"))[:2]:
        data = path.read_bytes()
        reduced = decode_rgb(data, path, min_size=(288, 288))
        paper = cv2.resize(decode_rgb(data, path), (288, 288), interpolation=cv2.INTER_AREA).astype(int)
        linear = cv2.resize(reduced, (288, 288), interpolation=cv2.INTER_LINEAR).astype(int)
        area = cv2.resize(reduced, (288, 288), interpolation=cv2.INTER_AREA).astype(int)
        # the DCT scaling has averaged 2x2 already: bilinear for the last 1.3x lands as close to the full-size
        # area resize as a second area average does (5 real tiles: 1.37-2.01 levels against 1.44-2.17)
        assert np.abs(linear - paper).mean() <= np.abs(area - paper).mean()


def test_other_formats_decode_at_full_size():
    png = cv2.imencode(".png", np.full((40, 40, 3), 9, np.uint8))[1].tobytes()
    assert decode_rgb(png, "tile.png", min_size=(5, 5)).shape == (40, 40, 3)


def cut_tail(data: bytes) -> bytes:
    return data[:len(data) - 300]


def cut_mid_scan(data: bytes) -> bytes:
    return data[:len(data) // 2] + b"\xff\xd9"


def header_promises_more(data: bytes) -> bytes:
    data = bytearray(data)
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = (4800).to_bytes(2, "big") + (3200).to_bytes(2, "big")
    return bytes(data)


@pytest.mark.parametrize("damage, why", [(cut_tail, "truncated JPEG: premature end"),
                                         (cut_mid_scan, "corrupt JPEG: .*premature end"),
                                         (header_promises_more, "corrupt JPEG")])
def test_a_damaged_jpeg_is_refused_at_reduced_scale(damage, why):
    data = damage(smooth_jpeg())
    if damage is not cut_tail:  # these OpenCV's libjpeg decodes at reduced scale, filling what is missing with grey
        assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_COLOR_8) is not None
    with pytest.raises(DatasetFileError, match=rf"bad.jpg: {why}"):
        decode_rgb(data, "bad.jpg", min_size=(70, 50))


def test_reduced_decoding_applies_to_resized_aerials_and_photos_only():
    cfg = CrossViewDataConfig(aerial_size=96, reduced_decode=True)
    assert decode_size(cfg, "aerial") == decode_size(cfg, "image") == (96, 96)
    assert decode_size(cfg, "panorama") is None and decode_size(cfg, "sphere") is None  # polar geometry, roll, fov
    polar = CrossViewDataConfig(alignment="polar", reduced_decode=True)
    assert decode_size(polar, "aerial") is None  # sampled by the polar transform
    assert decode_size(CrossViewDataConfig(), "aerial") is None  # off by default: older checkpoints decode as before


def spy_on_decodes(monkeypatch) -> list[dict]:
    """The keyword arguments of each strict JPEG decode from now on."""
    calls, real = [], simplejpeg.decode_jpeg

    def spy(data, *args, **kw):
        calls.append({k: v for k, v in kw.items() if k.startswith("min_")})
        return real(data, *args, **kw)

    monkeypatch.setattr(validate.simplejpeg, "decode_jpeg", spy)
    return calls


def test_the_data_module_reads_aerials_reduced_and_checks_files_at_full_size(tmp_path, monkeypatch):
    root = write_cvusa(tmp_path / "cvusa", n_train=3, n_val=2, aerial=128, pano=(32, 128))
    calls = spy_on_decodes(monkeypatch)
    cfg = CrossViewDataConfig(name="cvusa", root=str(root), aerial_size=32, pano_size=[16, 64], reduced_decode=True)
    split = read_split(cfg, {"name": "cvusa"}, "train")
    assert len(calls) == 6 and all(kw == {} for kw in calls)  # the start-up check: every file at full size
    del calls[:]
    item = CrossViewPairs(split, cfg, train=False)[1]
    assert calls == [{}, {"min_height": 32, "min_width": 32}]  # the panorama at full size, the aerial at 1/4
    aerial = split.references[1]
    reduced = image_tensor(align_reference(decode_rgb(aerial.read_bytes(), aerial, min_size=(32, 32)), cfg))
    full = image_tensor(align_reference(decode_rgb(aerial.read_bytes(), aerial), cfg))
    assert torch.equal(item["reference"], reduced) and not torch.equal(reduced, full)
    assert torch.equal(ViewImages(split.references, "aerial", cfg)[1]["image"], reduced)  # galleries too
    off = CrossViewDataConfig(name="cvusa", root=str(root), aerial_size=32, pano_size=[16, 64], reduced_decode=False)
    assert torch.equal(CrossViewPairs(cvusa(str(root), "train"), off, train=False)[1]["reference"], full)
