"""What one query may cost, and its settings, checked the same way by `geoloc serve` and localize.py
(geoloc/apps/query.py): a small fov, a long thin image, too many candidate headings or too large a topk is refused
with the limit and the value named, before anything is decoded or allocated; a bad setting names the field; a form
field given twice is refused; an upload is decoded strictly; /health answers while a request runs; the heading
search stops at the server's time limit; a bad device names the valid ones."""

from __future__ import annotations

import re
import threading
import time

import httpx
import numpy as np
import pytest
from conftest import CONF
from fastapi.testclient import TestClient
from hydra import compose, initialize_config_dir
from test_localize import gallery  # noqa: F401  (a fixture: a 1-epoch TINY checkpoint and its saved gallery)
from test_serve import RED, FakeLocalizer, assert_still_serving, jpeg, png, serving

from geoloc import cli
from geoloc.apps.localize import Localizer, read_street
from geoloc.apps.query import QueryError, QueryLimits, check_settings
from geoloc.apps.serve import create_app, upload
from geoloc.apps.serve.command import ServeConfig
from geoloc.config import ConfigError
from geoloc.data import io
from geoloc.launch.hydra_hooks import compose_checked


@pytest.fixture
def fake():
    return FakeLocalizer()


@pytest.fixture
def client(fake):
    return TestClient(create_app(fake))


def post(client, image: bytes, name: str = "pano.png", **fields):
    return client.post("/localize", files={"image": (name, image)}, data=fields)


# ---- the work one request can cause -----------------------------------------------------------------------------
SMALL_PANO = png(np.full((256, 512, 3), 90, np.uint8))  # a few kB


@pytest.mark.parametrize("fov,key,message", [
    # 512·360/0.1 = 1,843,200 columns: 1.4 GB of canvas at 256 rows, and an OpenCV assertion past 32,766 columns
    ("0.1", "max_canvas_side", (r"the upload 'pano.png', a fov=0.1 view 512 columns wide, is placed on a 360° "
                                r"canvas of 1,843,200 columns \(W·360/fov\), over the limit of 16,384 "
                                r"\(max_canvas_side\): give the image's true fov, or downscale it to at most 4 "
                                r"columns")),
    ("0.001", "max_canvas_side", r"canvas of 184,320,000 columns"),  # 141 GB asked for
    ("1e-300", "max_canvas_side", r"canvas of 1.84e\+305 columns .*true fov$"),
    ("1e-308", "max_canvas_side", r"canvas of inf columns"),  # W·360/fov overflows a float: still a clear 413
    ("5", "max_canvas_side", (r"a fov=5 view 512 columns wide, is placed on a 360° canvas of 36,864 columns.*"
                              r"over the limit of 16,384")),
])
def test_a_small_fov_is_refused_before_its_canvas_is_allocated(fake, fov, key, message, monkeypatch):
    allocated = []
    monkeypatch.setattr(upload, "decode_rgb", lambda *a, **k: allocated.append(1))
    client = TestClient(create_app(fake))
    answer = post(client, SMALL_PANO, fov=fov)
    assert answer.status_code == 413, answer.text
    assert answer.json()["key"] == key and re.search(message, answer.json()["detail"])
    assert allocated == [] and fake.calls == 0  # refused from the header: nothing decoded, nothing encoded
    monkeypatch.undo()
    assert_still_serving(client, fake)


def test_the_canvas_pixels_count_against_max_pixels(monkeypatch):
    fake = FakeLocalizer(limits=QueryLimits(max_pixels=400_000))
    client = TestClient(create_app(fake))
    answer = post(client, SMALL_PANO, fov="90")  # 131,072 pixels, on a 2,048 x 256 canvas: 524,288
    assert answer.status_code == 413 and answer.json()["key"] == "max_pixels"
    assert "360° canvas of 2,048 columns (W·360/fov) and 256 rows: 524,288 pixels, over the limit of 400,000" in \
        answer.json()["detail"]
    assert post(client, SMALL_PANO, fov="180").status_code == 200  # 1,024 x 256: within


def test_a_long_thin_image_is_refused_not_an_opencv_assertion(client, fake):
    answer = post(client, png(np.zeros((1, 65_500, 3), np.uint8)), name="strip.png")
    assert answer.status_code == 413, answer.text
    assert ("the upload 'strip.png', a fov=360 view 65,500 columns wide, is placed on a 360° canvas of 65,500 "
            "columns (W·360/fov), over the limit of 16,384 (max_canvas_side)") in answer.json()["detail"]
    tall = post(client, png(np.zeros((20_000, 1, 3), np.uint8)), name="tall.png")
    assert tall.status_code == 413 and "tall.png' is 20,000 rows high, over the limit of 16,384" in tall.text
    assert_still_serving(client, fake)


def test_limits_and_their_defaults_are_checked():
    assert QueryLimits() == QueryLimits(25_000_000, 16_384, 72, 100)
    with pytest.raises(ValueError, match="max_canvas_side=40000 is over 32,766, the most columns OpenCV's remap"):
        QueryLimits(max_canvas_side=40_000)
    with pytest.raises(ValueError, match="max_headings must be >= 1, got 0"):
        QueryLimits(max_headings=0)


@pytest.mark.parametrize("given,field,message", [
    ({"fov": "abc"}, "fov", "fov='abc' is not a number"), ({"fov": float("nan")}, "fov", "is not a finite number"),
    ({"fov": 0}, "fov", r"fov=0 is outside \(0, 360\]"), ({"fov": 360.5}, "fov", "is outside"),
    ({"fov": True}, "fov", "is not a number"), ({"topk": "abc"}, "topk", "topk='abc' is not a number"),
    ({"topk": 2.5}, "topk", "is not an integer"), ({"topk": 0}, "topk", "is below 1"),
    ({"heading": float("nan")}, "heading", "heading=nan is not a finite number"),
    ({"heading": "-inf"}, "heading", "is not a finite number"),
    ({"refine": "maybe"}, "refine", "refine='maybe' is not true or false"),
])
def test_one_check_of_the_settings_names_the_field(given, field, message):
    with pytest.raises(QueryError, match=message) as caught:
        check_settings(**given)
    assert caught.value.key == field and caught.value.status == 422
    ok = check_settings(fov="90", topk="3", heading="-45.5")
    assert (ok.fov, ok.topk, ok.heading) == (90.0, 3, -45.5)
    assert check_settings(topk=7.0).topk == 7 and check_settings().fov == 360.0  # the defaults: QuerySettings'
    assert check_settings(refine=" No ").refine is False and check_settings(refine=False).refine is False
    assert check_settings().refine is True


# ---- form fields once, strict decoding, /health, the time limit -------------------------------------------------
@pytest.mark.parametrize("request_,message", [
    ({"data": {"fov": ["90", "120"]}}, "form field 'fov' is given 2 times: give it once"),
    ({"data": {"heading": ["0", "30", "60"]}}, "form field 'heading' is given 3 times"),
    ({"params": [("topk", "1"), ("topk", "9")]}, "query parameter 'topk' is given 2 times"),
    ({"extra_files": [("image", ("b.png", png(RED)))]}, "form field 'image' is given 2 times"),
    ({"data": {"heding": "30"}}, "unknown form field 'heding': /localize takes the file field image and fov, topk"),
    ({"params": {"image": "x"}}, "unknown query parameter 'image'"),
])
def test_a_field_given_twice_or_unknown_is_refused_by_name(client, fake, request_, message):
    files = [("image", ("pano.png", png(RED)))] + request_.pop("extra_files", [])
    answer = client.post("/localize", files=files, **request_)
    assert answer.status_code == 422 and message in answer.json()["detail"], answer.text
    assert_still_serving(client, fake)


def cut_mid_scan(data: bytes) -> bytes:
    """A JPEG cut in the middle of its scan, with an end marker appended: its one FF D9 is at the end."""
    return data[: len(data) // 2].rstrip(b"\xff") + b"\xff\xd9"


def promising_more(data: bytes, height: int = 4999, width: int = 5000) -> bytes:
    """A complete JPEG whose frame header (SOF0) promises height x width pixels."""
    at = data.index(b"\xff\xc0") + 5
    return data[:at] + height.to_bytes(2, "big") + width.to_bytes(2, "big") + data[at + 4:]


NOISE = np.random.default_rng(3).integers(0, 255, (64, 128, 3), np.uint8)


@pytest.mark.parametrize("bad,message", [
    (cut_mid_scan(jpeg(NOISE)), r"the upload 'pano.jpg': corrupt JPEG: .*Send the complete file again"),
    (promising_more(jpeg(np.full((8, 8, 3), 128, np.uint8))), r"the upload 'pano.jpg': corrupt JPEG"),
])
def test_an_incomplete_jpeg_upload_is_refused_not_filled_with_grey(client, fake, bad, message):
    answer = post(client, bad, name="pano.jpg")
    assert answer.status_code == 400 and re.search(message, answer.json()["detail"]), answer.text
    assert fake.calls == 0
    assert_still_serving(client, fake)


def test_health_answers_while_a_request_holds_the_network():
    release, started = threading.Event(), threading.Event()

    class Blocking(FakeLocalizer):
        def localize(self, image, *args, **kwargs):
            started.set()
            assert release.wait(30), "the test never released the request"
            return super().localize(image, *args, **kwargs)

    fake = Blocking()
    with serving(create_app(fake)) as url:
        outcome = {}
        request = threading.Thread(target=lambda: outcome.update(
            answer=httpx.post(f"{url}/localize", files={"image": ("p.png", png(RED))}, timeout=60)))
        request.start()
        assert started.wait(30)
        try:
            health = httpx.get(f"{url}/health", timeout=5)  # while the request is inside the localizer
        finally:
            release.set()
            request.join(60)
    assert health.status_code == 200 and health.json()["status"] == "ok" and fake.active == 0
    assert outcome["answer"].status_code == 200


# ---- the real Localizer: the same checks, and a heading search a few candidates at a time -----------------------
@pytest.fixture(scope="module")
def loaded(gallery):  # noqa: F811
    root, ckpt, folder = gallery
    return root, ckpt, folder, Localizer.load(ckpt, folder, device="cpu", heading_steps=20)


@pytest.mark.slow
def test_the_localizer_checks_before_it_allocates_and_encodes_a_few_headings_at_a_time(loaded, monkeypatch):
    root, _, _, loc = loaded
    with pytest.raises(QueryError, match=r"a fov=0.1 view 64 columns wide, is placed on a 360° canvas of 230,400 "
                                         r"columns .*max_canvas_side") as caught:
        loc.localize(np.zeros((16, 64, 3), np.uint8), fov=0.1)
    assert caught.value.status == 413
    with pytest.raises(QueryError, match="65,500 columns"):
        loc.localize(np.zeros((1, 65_500, 3), np.uint8))
    with pytest.raises(QueryError, match="topk=101 is over the limit of 100"):
        loc.localize(np.zeros((16, 64, 3), np.uint8), topk=101)
    batches = []
    encode = loc.encoder.encode_street
    monkeypatch.setattr(loc.encoder, "encode_street", lambda x: batches.append(len(x)) or encode(x))
    image = read_street(root / "streetview/panos/0000013.jpg")
    answer = loc.localize(image, topk=3, heading="search")  # the search: this checkpoint would answer at north
    assert batches == [12, 8]  # 20 candidates, CANDIDATES_PER_PASS at a time
    inputs, _ = loc.encoder.street_inputs(image, 360.0, None, 20)
    scores = (encode(inputs) @ loc.index._descriptors.t()).max(dim=0).values  # every candidate in one pass
    assert [hit["row"] for hit in answer.topk] == scores.argsort(descending=True)[:3].tolist()
    assert answer.topk[0]["score"] == pytest.approx(float(scores.max()), abs=1e-5)


@pytest.mark.slow
def test_heading_steps_over_max_headings_is_refused_at_load(gallery):  # noqa: F811
    _, ckpt, folder = gallery
    with pytest.raises(QueryError, match=r"heading_steps=73 candidate headings is over max_headings=72"):
        Localizer.load(ckpt, folder, device="cpu", heading_steps=73)
    with pytest.raises(QueryError, match=r"heading_steps=9 .* over max_headings=8"):
        Localizer.load(ckpt, folder, device="cpu", heading_steps=9, limits=QueryLimits(max_headings=8))


def test_serve_checks_heading_steps_as_the_localizer_does_before_loading():
    with pytest.raises(QueryError, match=r"heading_steps=73 candidate headings is over max_headings=72"):
        ServeConfig(ckpt="x.pt", gallery="g", heading_steps=73)
    with pytest.raises(QueryError, match=r"heading_steps must be an integer >= 1, got 0"):
        ServeConfig(ckpt="x.pt", gallery="g", heading_steps=0)
    assert ServeConfig(ckpt="x.pt", gallery="g", heading_steps=8, max_headings=8).heading_steps == 8


@pytest.mark.slow
def test_the_heading_search_stops_at_the_servers_time_limit(loaded):
    root, _, _, loc = loaded
    image = read_street(root / "streetview/panos/0000013.jpg")
    with pytest.raises(QueryError, match="ran past its time limit before all its candidate headings") as caught:
        loc.localize(image, deadline=time.monotonic() - 1)
    assert caught.value.status == 503
    client = TestClient(create_app(loc, max_seconds=1e-9))  # any work outlasts it
    pano = (root / "streetview/panos/0000013.jpg").read_bytes()
    answer = client.post("/localize", files={"image": ("p.jpg", pano)})
    assert answer.status_code == 503 and "max_seconds=1e-09" in answer.json()["detail"]
    assert TestClient(create_app(loc)).post("/localize", files={"image": ("p.jpg", pano)}).status_code == 200


# ---- localize.py: the same checks, as a clear error naming the key ----------------------------------------------
def compose_localize(ckpt, folder, image, out, *overrides):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("localize", overrides=[f"ckpt={ckpt}", f"gallery={folder}", f"image={image}", f"out={out}",
                                              "device=cpu", "picture=false", *overrides])


@pytest.mark.parametrize("override,message", [
    ("heading=nan", r"localize.py: heading=nan is not a finite number \(the image's bearing"),
    ("fov=abc", r"localize.py: fov='abc' is not a number \(the horizontal field of view"),
    ("topk=abc", r"localize.py: topk='abc' is not a number"),
    ("fov=0", r"localize.py: fov=0 is outside \(0, 360\]"), ("fov=400", "is outside"),
    ("topk=0", "topk=0 is below 1"), ("topk=500", r"topk=500 is over the limit of 100 .*\(max_topk\)"),
    ("device=banana", "device='banana' is not a device: use one of auto, cpu"),
])
def test_localize_py_names_a_bad_setting_before_loading_anything(gallery, tmp_path, override, message):  # noqa: F811
    from geoloc.apps.localize.command import localize

    root, ckpt, folder = gallery
    with pytest.raises(ValueError, match=message):
        localize(compose_localize(ckpt, folder, root / "streetview/panos/0000013.jpg", tmp_path / "out", override))


@pytest.mark.slow
def test_localize_py_refuses_an_image_over_a_limit_from_its_header(gallery, tmp_path, monkeypatch):  # noqa: F811
    from geoloc.apps.localize.command import localize

    _, ckpt, folder = gallery
    strip = tmp_path / "strip.png"
    strip.write_bytes(png(np.zeros((1, 65_500, 3), np.uint8)))
    decoded = []
    monkeypatch.setattr(io, "decode_rgb", lambda *a, **k: decoded.append(1))  # what localize.py decodes with
    with pytest.raises(QueryError, match=rf"{strip}, a fov=360 view 65,500 columns wide.*max_canvas_side"):
        localize(compose_localize(ckpt, folder, strip, tmp_path / "out"))
    small = tmp_path / "small.png"
    small.write_bytes(png(np.zeros((16, 64, 3), np.uint8)))
    with pytest.raises(QueryError, match=r"a fov=0.5 view 64 columns wide.*46,080 columns"):
        localize(compose_localize(ckpt, folder, small, tmp_path / "out2", "fov=0.5"))
    assert decoded == []


def test_an_image_its_exif_orientation_turns_is_held_to_the_limits_as_decoded(gallery, tmp_path):  # noqa: F811
    """A PNG whose EXIF orientation turns it as it is decoded: its header (64 wide, 5,000 high) is within the limits
    at fov=90, the decoded image (5,000 wide) is not, and is refused naming the file, not handed to OpenCV."""
    from PIL import Image

    from geoloc.apps.localize.command import localize

    _, ckpt, folder = gallery
    turned = tmp_path / "turned.png"
    exif = Image.Exif()
    exif[0x0112] = 6  # Orientation: rotate 90° clockwise to display
    Image.fromarray(np.zeros((5_000, 64, 3), np.uint8)).save(turned, exif=exif.tobytes())
    assert read_street(turned).shape == (64, 5_000, 3)
    with pytest.raises(QueryError, match=rf"^{turned}, a fov=90 view 5,000 columns wide, is placed on a 360° canvas "
                                         r"of 20,000 columns .*\(max_canvas_side\)"):
        localize(compose_localize(ckpt, folder, turned, tmp_path / "out", "fov=90", "heading=0"))


def test_a_bad_device_names_the_valid_ones_before_the_checkpoint_is_read(capsys):
    assert cli.main(["serve", "ckpt=no/such.pt", "gallery=g", "device=banana"]) == 2
    assert "geoloc serve: device='banana' is not a device: use one of auto, cpu" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="bad 'serve' config: max_topk must be >= 1"):
        compose_checked("serve", ServeConfig, ["ckpt=a", "gallery=g", "max_topk=0"], "serve")


def test_a_panorama_with_no_horizon_rows_is_refused_naming_the_file(gallery, tmp_path, monkeypatch):  # noqa: F811
    """A 1-row image against a full-sphere gallery (VIGOR's queries): its horizon band, rows H/4 to 3H/4, is empty.
    The service answers 422 naming the upload; localize.py refuses a folder holding one before it answers any
    image, naming the file."""
    from geoloc.apps.localize.command import localize

    _, ckpt, folder = gallery
    loaded = Localizer.load(ckpt, folder, device="cpu")
    sphere = Localizer(loaded.encoder, loaded.index, loaded.places, {**loaded.meta, "query_view": "sphere"})
    client = TestClient(create_app(sphere))
    answer = post(client, png(np.zeros((1, 64, 3), np.uint8)), name="strip.png", heading="0")
    assert answer.status_code == 422, answer.text
    assert answer.json()["key"] == "image" and answer.json()["detail"].startswith(
        "the upload 'strip.png' is 64x1: the street view cut from it has no rows")
    assert post(client, png(np.zeros((2, 64, 3), np.uint8)), heading="0").status_code == 200  # one row of band

    images = tmp_path / "images"
    images.mkdir()
    for name, rows in (("a.png", 16), ("b.png", 1), ("c.png", 16)):
        (images / name).write_bytes(png(np.zeros((rows, 64, 3), np.uint8)))
    monkeypatch.setattr(Localizer, "load", lambda *args, **kwargs: sphere)
    with pytest.raises(QueryError, match=rf"^{images / 'b.png'} is 64x1: the street view cut from it has no rows"):
        localize(compose_localize(ckpt, folder, images, tmp_path / "out", "heading=0"))
    assert not (tmp_path / "out" / "localize.jsonl").exists()  # refused before the first answer, a.png's too
