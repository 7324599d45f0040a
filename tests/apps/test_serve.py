"""`geoloc serve`: /health and /localize answer a fake localizer; every bad upload gets its 4xx with a message
and the next good request still succeeds; a failing localizer gets a 500; concurrent requests through a real
uvicorn all succeed, each with its own image's answer, one at a time inside the localizer."""

from __future__ import annotations

import contextlib
import json
import re
import socket
import struct
import sys
import threading
import time
import types
import zlib
from concurrent.futures import ThreadPoolExecutor

import anyio
import cv2
import httpx
import numpy as np
import pytest
import uvicorn
from fastapi.testclient import TestClient
from geoloc import cli
from geoloc.apps.query import QueryLimits, check_settings, check_size
from geoloc.apps.serve import create_app, upload
from geoloc.apps.serve.command import ServeConfig
from geoloc.launch.hydra_hooks import compose_checked
from test_localize import gallery  # noqa: F401  (a fixture: a 1-epoch TINY checkpoint and its saved gallery)

from conftest import REPO


class FakeLocalizer:
    """The duck-typed interface of geoloc.apps.localize.Localizer; its answer is computed from the pixels it got."""

    def __init__(self, delay: float = 0.0, fail_on: str | None = None, limits: QueryLimits | None = None):
        self.delay, self.fail_on, self.limits = delay, fail_on, limits or QueryLimits()
        self.calls = self.active = self.most_active = 0
        self._counter = threading.Lock()

    def info(self) -> dict:
        return {"checkpoint": "fake.pt", "gallery_size": 3, "dim": 8, "device": "cpu"}

    def parse(self, **given):
        """The Localizer's parse of the settings as sent."""
        return check_settings(**given, max_topk=self.limits.max_topk)

    def check(self, width, height, query, name="the image"):
        """The Localizer's check, on a panorama's canvas (rows H, columns W·360/fov)."""
        check_size(name, width, height, query.fov, (height, width * 360.0 / query.fov), self.limits)

    def localize(self, image, query, name=None, deadline=None) -> dict:
        fov, topk = query.fov, query.topk
        known = {key: getattr(query, key) for key in ("heading", "heading_prior", "abstain")
                 if getattr(query, key) is not None}
        with self._counter:
            self.calls += 1
            self.active += 1
            self.most_active = max(self.most_active, self.active)
        try:
            time.sleep(self.delay)
            if name == self.fail_on:
                raise RuntimeError("the gallery file vanished")
            if name == "nan.png":
                return {"score": float("nan")}
            mean_rgb = [round(float(c), 3) for c in image.reshape(-1, 3).mean(axis=0)]
            return {"name": name, "shape": list(image.shape), "dtype": str(image.dtype), "mean_rgb": mean_rgb,
                    "fov": fov, "known": known, "topk": [{"rank": r + 1, "reference": f"ref{r}"} for r in range(topk)],
                    "heading_deg": 0.0, "position": {"x": 0.0, "y": 0.0}}
        finally:
            with self._counter:
                self.active -= 1


def png(rgb: np.ndarray) -> bytes:
    return cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))[1].tobytes()


def jpeg(rgb: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]))[1].tobytes()


def png_chunks(width: int, height: int, idat: bytes) -> bytes:
    """A greyscale 8-bit PNG with the given IHDR size and IDAT payload."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def decompression_bomb(width: int = 10_000, height: int = 5_000) -> bytes:
    """A complete, valid all-black PNG of width x height (50 megapixels): about 50 kB that inflate to 50 MB."""
    deflate = zlib.compressobj(9)
    row = bytes(width + 1)  # filter byte 0, then the row
    idat = b"".join(deflate.compress(row) for _ in range(height)) + deflate.flush()
    return png_chunks(width, height, idat)


RED = np.zeros((40, 80, 3), np.uint8)
RED[..., 0] = 255
GOOD = {"files": {"image": ("pano.png", png(RED), "image/png")}}
TEXT = b"hello, this is not a picture\n" * 4
TRUNCATED_JPEG = jpeg(np.random.default_rng(0).integers(0, 255, (64, 128, 3), np.uint8))[:800]
CORRUPT_PNG = png_chunks(8, 8, bytes(range(7, 200)))  # complete chunks, but the IDAT is not a zlib stream


@pytest.fixture
def client(fake):
    return TestClient(create_app(fake, max_bytes=1_000_000))


@pytest.fixture
def fake():
    return FakeLocalizer(limits=QueryLimits(max_pixels=30_000_000))


def assert_still_serving(client, fake):
    answer = client.post("/localize", **GOOD)
    assert answer.status_code == 200, answer.text
    assert fake.calls == 1  # the bad request before never reached the localizer


def test_health_reports_the_localizer_info(client):
    answer = client.get("/health")
    assert answer.status_code == 200
    assert answer.json() == {"status": "ok", "checkpoint": "fake.pt", "gallery_size": 3, "dim": 8, "device": "cpu"}


def test_localize_hands_the_localizer_an_rgb_array_and_returns_its_answer(client, fake):
    answer = client.post("/localize", **GOOD)
    assert answer.status_code == 200, answer.text
    body = answer.json()
    # red stays red: OpenCV's BGR is turned to RGB, and the size is H x W x 3
    assert body["mean_rgb"] == [255.0, 0.0, 0.0] and body["shape"] == [40, 80, 3] and body["dtype"] == "uint8"
    assert body["name"] == "pano.png" and body["fov"] == 360.0 and len(body["topk"]) == 5  # the defaults
    grey = client.post("/localize", files={"image": ("g.png", png(np.full((20, 30, 3), 9, np.uint8)))})
    assert grey.json()["mean_rgb"] == [9.0, 9.0, 9.0] and fake.calls == 2


@pytest.mark.parametrize("how", ["form", "query"])
def test_fov_topk_and_heading_come_as_form_fields_or_query_parameters(client, how):
    fields = {"fov": "90", "topk": "2", "heading": "-45.5"}
    kwargs = {"data": fields} if how == "form" else {"params": fields}
    body = client.post("/localize", **GOOD, **kwargs).json()
    assert body["fov"] == 90.0 and [hit["rank"] for hit in body["topk"]] == [1, 2]
    assert body["known"] == {"heading": -45.5}
    assert client.post("/localize", **GOOD).json()["known"] == {}  # no heading: the localizer searches it


def test_a_setting_given_both_as_form_and_query_is_refused(client, fake):
    answer = client.post("/localize", **GOOD, data={"fov": "90"}, params={"fov": "120"})
    assert answer.status_code == 422 and "fov is given both as a form field and as a query" in answer.json()["detail"]
    assert_still_serving(client, fake)


BAD_UPLOADS = {  # name: (request, status, what the message must say)
    "text": ({"files": {"image": ("notes.txt", TEXT, "text/plain")}}, 415,
             r"the upload 'notes.txt' is not an image \(it starts with b'hello, this is n'\).* -F image=@"),
    "empty file": ({"files": {"image": ("pano.jpg", b"", "image/jpeg")}}, 400, r"'pano.jpg' is empty \(0 bytes\)"),
    "empty body": ({}, 400, r"the request body is empty: send the street image as the multipart/form-data file"),
    "wrong field": ({"files": {"file": ("pano.png", png(RED), "image/png")}}, 422,
                    r"unknown form field 'file': /localize takes the file field image and fov, topk, heading"),
    "truncated jpeg": ({"files": {"image": ("cut.jpg", TRUNCATED_JPEG)}}, 400,
                       r"the upload 'cut.jpg': truncated JPEG.*Send the complete file"),
    "corrupt png": ({"files": {"image": ("bad.png", CORRUPT_PNG)}}, 400,
                    r"the upload 'bad.png': corrupt image: does not decode\. Send the complete file again"),
    "fov 0": ({**GOOD, "data": {"fov": "0"}}, 422,
              r"form field fov='0' is outside \(0, 360\] \(the horizontal field of view in degrees, in \(0,"),
    "fov 361": ({**GOOD, "params": {"fov": "361"}}, 422,
                r"query parameter fov='361' is outside \(0, 360\] \(the horizontal field of view"),
    "fov -1": ({**GOOD, "data": {"fov": "-1"}}, 422, r"form field fov='-1' is outside \(0, 360\]"),
    "fov nan": ({**GOOD, "data": {"fov": "nan"}}, 422, r"form field fov='nan' is not a finite number"),
    "fov text": ({**GOOD, "data": {"fov": "abc"}}, 422, r"form field fov='abc' is not a number \(the horizontal"),
    "topk 0": ({**GOOD, "data": {"topk": "0"}}, 422,
               r"form field topk='0' is below 1 \(how many references to return"),
    "topk text": ({**GOOD, "data": {"topk": "abc"}}, 422, r"form field topk='abc' is not a number"),
    "topk over max_topk": ({**GOOD, "data": {"topk": "101"}}, 413,
                           r"topk=101 is over the limit of 100 references an answer lists \(max_topk\)"),
    "heading inf": ({**GOOD, "data": {"heading": "inf"}}, 422,
                    r"form field heading='inf' is not a finite number \(the image's bearing in degrees"),
    "heading nan": ({**GOOD, "params": {"heading": "nan"}}, 422, r"query parameter heading='nan' is not a finite"),
    "topk 1.5": ({**GOOD, "params": {"topk": "1.5"}}, 422, r"query parameter topk='1.5' is not an integer"),
}


@pytest.mark.parametrize("name", BAD_UPLOADS)
def test_a_bad_request_gets_its_4xx_with_a_message_and_the_server_goes_on(client, fake, name):
    request, status, message = BAD_UPLOADS[name]
    answer = client.post("/localize", **request)
    assert answer.status_code == status, answer.text
    assert answer.json()["detail"] and re.search(message, answer.json()["detail"]), answer.text
    assert_still_serving(client, fake)


def test_a_decompression_bomb_is_refused_from_its_header_without_decoding(client, fake, monkeypatch):
    bomb = decompression_bomb()
    assert len(bomb) < 100_000  # small on the wire: only the header check can stop it
    decoded = []
    monkeypatch.setattr(upload, "decode_rgb", lambda *a, **k: decoded.append(1))
    answer = client.post("/localize", files={"image": ("bomb.png", bomb, "image/png")})
    assert answer.status_code == 413, answer.text
    assert ("the upload 'bomb.png' is 10000x5000 = 50,000,000 pixels, over the limit of 30,000,000 (max_pixels): "
            "downscale it" in answer.json()["detail"]) and answer.json()["key"] == "max_pixels"
    assert decoded == []
    monkeypatch.undo()
    assert_still_serving(client, fake)


def test_a_body_over_the_byte_limit_gets_413_declared_or_streamed(fake):
    client = TestClient(create_app(fake, max_bytes=5_000))
    noise = png(np.random.default_rng(1).integers(0, 255, (64, 64, 3), np.uint8))  # ~12 kB, incompressible
    declared = client.post("/localize", files={"image": ("noise.png", noise, "image/png")})
    assert declared.status_code == 413 and "over this server's limit of 5,000 bytes (max_bytes)" in declared.text
    # without a Content-Length (chunked): counted as it arrives
    body = (b'--b0undary\r\nContent-Disposition: form-data; name="image"; filename="noise.png"\r\n'
            b"Content-Type: image/png\r\n\r\n" + noise + b"\r\n--b0undary--\r\n")
    streamed = client.post("/localize", content=iter([body[i:i + 1024] for i in range(0, len(body), 1024)]),
                           headers={"content-type": "multipart/form-data; boundary=b0undary"})
    assert streamed.status_code == 413 and "(max_bytes)" in streamed.text
    assert fake.calls == 0
    assert_still_serving(client, fake)


def test_a_declared_content_length_over_the_limit_is_refused_unread(fake):
    app, sent = create_app(fake, max_bytes=5_000), []

    async def receive():
        raise AssertionError("the body was read")

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "method": "POST", "path": "/localize", "headers": [(b"content-length", b"10000000000")],
             "query_string": b"", "root_path": "", "scheme": "http", "server": ("test", 80), "http_version": "1.1"}
    anyio.run(app, scope, receive, send)
    assert sent[0]["status"] == 413 and b"limit of 5,000 bytes" in sent[1]["body"]


@pytest.mark.parametrize("name,message", [
    ("boom.png", "localization failed: RuntimeError: the gallery file vanished. The server is still up"),
    ("nan.png", "localization failed: ValueError: Out of range float values are not JSON compliant"),
])
def test_a_failure_inside_the_localizer_is_a_500_with_its_message_and_the_server_goes_on(name, message):
    fake = FakeLocalizer(fail_on="boom.png")
    client = TestClient(create_app(fake))
    answer = client.post("/localize", files={"image": (name, png(RED), "image/png")})
    assert answer.status_code == 500 and message in answer.json()["detail"]
    assert client.post("/localize", **GOOD).status_code == 200


@pytest.fixture(scope="module")
def real_localizer(gallery):  # noqa: F811
    from geoloc.apps.localize import Localizer

    root, ckpt, folder = gallery
    return root, Localizer.load(ckpt, folder, device="cpu")


@pytest.mark.slow
@pytest.mark.parametrize("fields", [{"topk": "3"}, {"topk": "2", "fov": "120", "heading": "30"}])
def test_the_real_localizer_answers_through_the_service_exactly_as_when_called(real_localizer, fields):
    from geoloc.apps.localize import read_street

    root, localizer = real_localizer
    client = TestClient(create_app(localizer))
    health = client.get("/health").json()
    assert health["status"] == "ok" and health["gallery_size"] == 8 and health["device"] == "cpu"
    pano = max((root / "streetview" / "panos").glob("*.jpg"))  # a query of the gallery's split
    served = client.post("/localize", files={"image": (pano.name, pano.read_bytes(), "image/jpeg")}, data=fields)
    assert served.status_code == 200, served.text
    settings = {key: float(value) for key, value in fields.items() if key != "topk"}
    direct = localizer.localize(read_street(pano), topk=int(fields["topk"]), name=pano.name, **settings)
    assert served.json() == json.loads(json.dumps(direct.to_json())) and len(direct.topk) == int(fields["topk"])


@contextlib.contextmanager
def serving(app):
    """`app` under a real uvicorn on a free loopback port, in a thread; yields the base URL."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert server.started, "uvicorn did not start"
    try:
        yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()


def test_concurrent_requests_all_succeed_each_with_its_own_answer_one_at_a_time():
    fake = FakeLocalizer(delay=0.01)  # long enough for requests to overlap if nothing kept them apart
    images = [np.full((24, 48, 3), value, np.uint8) for value in (10, 200)]
    with serving(create_app(fake)) as url:

        def client_thread(t: int) -> list[tuple[int, int, dict]]:
            answers = []
            with httpx.Client(base_url=url, timeout=30) as http:
                for _ in range(3):
                    answer = http.post("/localize", files={"image": (f"{t}.png", png(images[t % 2]))})
                    answers.append((t % 2, answer.status_code, answer.json()))
            return answers

        with ThreadPoolExecutor(8) as pool:
            answers = [a for batch in pool.map(client_thread, range(8)) for a in batch]
        health = httpx.get(f"{url}/health", timeout=10)
    assert len(answers) == 24 and [status for _, status, _ in answers] == [200] * 24
    for which, _, body in answers:  # every answer is the one for the image that request sent
        assert body["mean_rgb"] == [float(images[which][0, 0, 0])] * 3
    assert fake.calls == 24 and fake.most_active == 1
    assert health.status_code == 200


def test_geoloc_serve_loads_the_localizer_once_and_runs_uvicorn(monkeypatch):
    loads, runs = [], []

    class Localizer:
        @classmethod
        def load(cls, ckpt, gallery_dir, device=None, heading_steps=36, limits=None):
            loads.append((ckpt, gallery_dir, device, heading_steps))
            return FakeLocalizer(limits=limits)

    monkeypatch.setitem(sys.modules, "geoloc.apps.localize", types.SimpleNamespace(Localizer=Localizer))
    monkeypatch.setattr(uvicorn, "run", lambda app, host, port: runs.append((app, host, port)))
    assert cli.main(["serve", "ckpt=run/best.pt", "gallery=run/gallery", "port=8123", "max_pixels=100",
                     "heading_steps=12"]) == 0
    assert loads == [("run/best.pt", "run/gallery", None, 12)]  # no device given: the encoder's rule (auto)
    (app, host, port), = runs
    assert (host, port) == ("127.0.0.1", 8123)
    answer = TestClient(app).post("/localize", **GOOD)  # max_pixels=100 reached the app: 80x40 is over it
    assert answer.status_code == 413
    assert "80x40 = 3,200 pixels, over the limit of 100 (max_pixels)" in answer.json()["detail"]
    assert TestClient(app).get("/docs").status_code == 404  # FastAPI's CDN pages: only with api_docs=true
    assert cli.main(["serve", "ckpt=run/best.pt", "gallery=run/gallery", "api_docs=true"]) == 0
    assert TestClient(runs[-1][0]).get("/docs").status_code == 200


@pytest.mark.parametrize("argv,code,message", [
    (["--help"], 0, "usage: geoloc SUBCOMMAND key=value"),
    (["serve", "--help"], 0, "usage: geoloc serve ckpt=PATH gallery=DIR"),
    (["locate"], 2, "geoloc: unknown subcommand 'locate'"),
    (["serve", "gallery=g"], 2, "missing mandatory value: ckpt"),
    (["serve", "ckpt=a", "gallery=g", "prt=80"], 2, "geoloc serve: bad 'serve' config: Could not override 'prt'.\n"),
    (["serve", "ckpt=a", "gallery=g", "+prt=80"], 2, "Key 'prt' not in 'ServeConfig'"),
    (["serve", "ckpt=a", "gallery=g", "port=http"], 2, "'http' of type 'str' could not be converted to Integer"),
    (["serve", "ckpt", "gallery=g"], 2, "bad 'serve' config: Error parsing override 'ckpt' missing EQUAL"),
    (["serve", "ckpt=a", "gallery=g", "port=80,81"], 2, "Ambiguous value for argument 'port=80,81'"),
    (["serve", "ckpt=no/such.pt", "gallery=g"], 2, "geoloc serve: checkpoint not found: no/such.pt"),
])
def test_the_console_script_explains_its_usage_and_bad_arguments(capsys, argv, code, message):
    assert cli.main(argv) == code
    assert message in capsys.readouterr()[0 if code == 0 else 1]


def test_geoloc_conf_serve_yaml_is_serve_config_with_its_defaults():
    composed = compose_checked("serve", ServeConfig, ["ckpt=a", "gallery='g,1'"], "serve")  # Hydra's quoting
    assert composed == ServeConfig(ckpt="a", gallery="g,1")


def test_pyproject_declares_the_script_and_ci_installs_the_serve_extra():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert project["scripts"]["geoloc"] == "geoloc.cli:main"
    extras = project["optional-dependencies"]
    names = {req.split(">")[0].split("=")[0] for req in extras["serve"]}
    assert {"fastapi", "uvicorn", "python-multipart"} <= names
    assert set(extras["serve"]) <= set(extras["dev"]) and any(req.startswith("httpx") for req in extras["dev"])
