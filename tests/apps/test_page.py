"""The service's page and tile routes on a fake localizer: the page and its script are served with a strict
Content-Security-Policy, the script never writes HTML, /tiles/{row} serves the row's file with bounds checks, and no
response carries a CORS header, even to a request from another origin."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient
from geoloc.apps.query import QueryError
from geoloc.apps.serve import create_app
from geoloc.apps.serve.page import STATIC
from test_serve import GOOD, FakeLocalizer


class TiledLocalizer(FakeLocalizer):
    def __init__(self, folder):
        super().__init__()
        self.folder = folder

    def tile(self, row):  # the Localizer's rule, on three files
        files = ["a.png", "b.jpg", "c.gif"]
        if not (str(row).isascii() and str(row).isdigit()) or int(row) >= len(files):
            raise QueryError("row", f"tile row {row!r} is not a gallery row: give an integer from 0 to 2", 404)
        return self.folder / files[int(row)]


@pytest.fixture
def tiled(tmp_path):
    (tmp_path / "a.png").write_bytes(b"\x89PNG fake tile a")
    (tmp_path / "b.jpg").write_bytes(b"\xff\xd8 fake tile b")
    (tmp_path / "c.gif").write_bytes(b"GIF89a")
    return TestClient(create_app(TiledLocalizer(tmp_path)))


def test_the_page_and_its_script_are_served_with_a_strict_policy(tiled):
    page = tiled.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "<script>" not in page.text  # no inline script
    # route.js after page.js, whose helpers it uses
    assert page.text.index('<script src="/page.js"></script>') < page.text.index('<script src="/route.js"></script>')
    policy = page.headers["content-security-policy"]
    assert "script-src 'self'" in policy and "default-src 'none'" in policy and "http" not in policy
    for name in ("page.js", "route.js"):
        script = tiled.get(f"/{name}")
        assert script.status_code == 200 and script.headers["content-type"].startswith("text/javascript")
        assert script.headers["content-security-policy"] == policy
        assert script.text == (STATIC / name).read_text()
    assert tiled.get("/app.js").status_code == 404 and tiled.get("/..%2Fpage.py.js").status_code == 404
    # nothing from another host, and nothing an answer holds is ever parsed as HTML
    for name in ("index.html", "page.js", "route.js"):
        source = (STATIC / name).read_text()
        assert not re.search(r"https?://", source), name
        assert not re.search(r"innerHTML|outerHTML|insertAdjacentHTML|document\.write|eval\(", source), name


def test_tiles_are_served_by_row_with_bounds_checks(tiled):
    got = tiled.get("/tiles/1")
    assert got.status_code == 200 and got.content == b"\xff\xd8 fake tile b"
    assert got.headers["content-type"] == "image/jpeg" and got.headers["x-content-type-options"] == "nosniff"
    assert tiled.get("/tiles/0").headers["content-type"] == "image/png"
    for row in ("3", "-1", "abc", "1.0", "%C2%B2", "99999999999999999999"):
        bad = tiled.get(f"/tiles/{row}")
        assert bad.status_code == 404 and "is not a gallery row" in bad.json()["detail"], row
    assert tiled.get("/tiles/2").status_code == 415  # a listed file that is not an image is not served


def test_no_response_carries_cors_headers(tiled):
    origin = {"Origin": "https://elsewhere.example"}
    answers = [tiled.get("/", headers=origin), tiled.get("/health", headers=origin),
               tiled.get("/tiles/0", headers=origin), tiled.post("/localize", headers=origin, **GOOD),
               tiled.options("/localize", headers={**origin, "Access-Control-Request-Method": "POST"})]
    assert answers[3].status_code == 200
    for answer in answers:
        assert not [h for h in answer.headers if h.lower().startswith("access-control-")], answer.request.url


class BrokenLocalizer(TiledLocalizer):
    def info(self):
        raise RuntimeError("a bug past every handler")


def test_api_docs_are_off_unless_asked_and_every_response_has_a_policy_and_frame_protection(tmp_path):
    """/docs and /redoc load FastAPI's scripts from a CDN: off by default. Every response, errors and Starlette's
    own 500 included, forbids framing and carries a Content-Security-Policy; the page keeps its own."""
    (tmp_path / "a.png").write_bytes(b"\x89PNG fake tile a")
    client = TestClient(create_app(BrokenLocalizer(tmp_path)), raise_server_exceptions=False)
    assert client.get("/docs").status_code == 404 and client.get("/redoc").status_code == 404
    answers = {"page": client.get("/"), "script": client.get("/page.js"), "tile": client.get("/tiles/0"),
               "localize": client.post("/localize", **GOOD), "openapi": client.get("/openapi.json"),
               "bad request": client.post("/localize", files={"image": ("a.txt", b"text")}),
               "no such row": client.get("/tiles/9"), "no such path": client.get("/nowhere"),
               "500": client.get("/health")}
    assert [answers[k].status_code for k in ("localize", "openapi", "bad request", "no such row", "500")] == [
        200, 200, 415, 404, 500]
    for name, answer in answers.items():
        policy = answer.headers["content-security-policy"]
        assert "frame-ancestors 'none'" in policy and "default-src 'none'" in policy, name
        assert answer.headers["x-frame-options"] == "DENY" and answer.headers["x-content-type-options"] == "nosniff"
        if name not in ("page", "script"):
            assert "script-src" not in policy, name  # nothing runs in an answer, a tile or an error
    assert answers["page"].headers["content-security-policy"].startswith("default-src 'none'; script-src 'self'; "
                                                                         "connect-src 'self'")
    docs = TestClient(create_app(TiledLocalizer(tmp_path), api_docs=True))
    for path in ("/docs", "/redoc"):
        page = docs.get(path)
        assert page.status_code == 200 and "cdn.jsdelivr.net" in page.text
        assert "script-src 'self' 'unsafe-inline' https://cdn.jsdelivr.net" in page.headers["content-security-policy"]
        assert page.headers["x-frame-options"] == "DENY"
    assert "script-src" not in docs.get("/health").headers["content-security-policy"]
