"""POST /localize/route: a route's frames and odometry in one request through a fake localizer whose gallery has
positions; the track has one estimate per frame and equals localize.py's fusion of the same answers; every bad
request is a 4xx naming what is wrong, before any frame is answered."""

from __future__ import annotations

import types

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from geoloc.apps.localize.route import fused, route_plane
from geoloc.apps.query import QueryLimits, check_settings, check_size
from geoloc.apps.serve import create_app
from geoloc.sequence.odometry import odometry_text, parse_odometry
from geoloc.sequence.particle_filter import FilterConfig

TILES = np.array([[e, n] for e in range(0, 400, 35) for n in range(0, 400, 35)], np.float64)  # x/y metres


class Result:
    """A LocalizationResult's duck: topk rows and scores, the top-1 position."""

    def __init__(self, rows, scores):
        self.topk = [{"row": int(r), "score": float(s), "x_m": float(TILES[r][0]), "y_m": float(TILES[r][1])}
                     for r, s in zip(rows, scores)]
        self.position, self.refined_position = {"x_m": self.topk[0]["x_m"], "y_m": self.topk[0]["y_m"]}, None

    def to_json(self):
        return {"topk": self.topk, "position": self.position}


class RouteLocalizer:
    """Answers a frame by its mean brightness: frame b's top-3 are the tiles b, b + 1, b + 2 (scores falling)."""

    def __init__(self, places=True, extent=np.full((len(TILES), 2), 70.0)):
        self.limits, self.calls = QueryLimits(), 0
        if places:  # what route_plane and named_tiles read of a gallery's places
            self.places = types.SimpleNamespace(kind="xy", reference_positions=TILES, reference_extent_m=extent)

    def parse(self, **given):
        return check_settings(**given, max_topk=self.limits.max_topk)

    def check(self, width, height, query, name="the image"):
        check_size(name, width, height, query.fov, (height, width * 360.0 / query.fov), self.limits)

    def localize(self, image, query, name=None, deadline=None):
        self.calls += 1
        b = int(image.mean()) % (len(TILES) - 3)
        return Result([b, b + 1, b + 2], [0.9, 0.8, 0.7])

    def info(self):
        return {"gallery_size": len(TILES)}


def frame(value: int) -> bytes:
    return cv2.imencode(".png", np.full((16, 64, 3), value, np.uint8))[1].tobytes()


def post(client, values, odometry: str, **extra):
    files = [("frames", (f"f{i}.png", frame(v), "image/png")) for i, v in enumerate(values)]
    files.append(("odometry", ("odometry.csv", odometry.encode(), "text/csv")))
    return client.post("/localize/route", files=files, data={"topk": "3", **extra})


def test_a_route_request_answers_each_frame_and_fuses_them_as_localize_py_does():
    localizer = RouteLocalizer()
    config = FilterConfig(particles=300)
    client = TestClient(create_app(localizer, route=config))
    odometry = odometry_text([0.0, 10.0, 10.0], [0.0, 0.0, 0.0])
    response = post(client, [5, 6, 7], odometry)
    assert response.status_code == 200, response.text
    body = response.json()
    assert [f["frame"] for f in body["frames"]] == ["f0.png", "f1.png", "f2.png"] and len(body["answers"]) == 3
    for line in body["frames"]:
        assert set(line["position"]) == {"x_m", "y_m"} and np.array(line["covariance_m2"]).shape == (2, 2)
    # the same answers fused by localize.py's path give the same track
    results = [Result([b, b + 1, b + 2], [0.9, 0.8, 0.7]) for b in (5, 6, 7)]
    expected = fused(route_plane(localizer.places, config), ["f0.png", "f1.png", "f2.png"], results,
                     parse_odometry(odometry.encode(), "odometry.csv"), config).lines
    assert body["frames"] == expected


@pytest.mark.parametrize("extent", [np.array([[60.0 + r, 70.0 + r] for r in range(len(TILES))]), None])
def test_a_route_answer_names_the_tiles_its_frames_answered_with_their_centres_and_extents(extent):
    client = TestClient(create_app(RouteLocalizer(extent=extent), route=FilterConfig(particles=300)))
    response = post(client, [5, 6, 5], odometry_text([0.0, 10.0, 10.0], [0.0, 0.0, 0.0]))
    assert response.status_code == 200, response.text
    body = response.json()
    # each distinct row of the answers' top-k once, in the order first named: frame 5's 5, 6, 7, then frame 6's 8
    rows = [5, 6, 7, 8]
    assert [t["row"] for t in body["tiles"]] == rows == list(dict.fromkeys(
        hit["row"] for answer in body["answers"] for hit in answer["topk"]))
    for tile, row in zip(body["tiles"], rows):
        assert tile == {"row": row, "x_m": TILES[row][0], "y_m": TILES[row][1],
                        "extent_m": None if extent is None else [60.0 + row, 70.0 + row]}


@pytest.mark.parametrize("case, status, words", [
    ("rows", 400, "2 rows for 3 frames"),
    ("bad_odometry", 400, "odometry: the upload 'odometry.csv'"),
    ("too_many", 413, "at most max_frames=2"),
    ("unknown", 422, "unknown form field 'speed'"),
    ("twice", 422, "'odometry' is given 2 times"),
    ("not_image", 415, "f1.png"),
])
def test_a_bad_route_request_is_refused_naming_why_before_any_frame_is_answered(case, status, words):
    localizer = RouteLocalizer()
    client = TestClient(create_app(localizer, route=FilterConfig(particles=300), max_frames=2 if case == "too_many"
                                   else None))
    good = odometry_text([0.0, 10.0, 10.0], [0.0, 0.0, 0.0])
    files = [("frames", (f"f{i}.png", frame(5 + i), "image/png")) for i in range(3)]
    odometry = {"rows": odometry_text([0.0, 10.0], [0.0, 0.0]),
                "bad_odometry": "frame,distance_m,heading_change_deg\n0,0,0\n1,-3,0\n2,1,0\n"}.get(case, good)
    files.append(("odometry", ("odometry.csv", odometry.encode(), "text/csv")))
    if case == "twice":
        files.append(("odometry", ("again.csv", good.encode(), "text/csv")))
    if case == "not_image":
        files[1] = ("frames", ("f1.png", b"not an image at all", "image/png"))
    data = {"topk": "3", **({"speed": "3"} if case == "unknown" else {})}
    response = client.post("/localize/route", files=files, data=data)
    assert response.status_code == status, response.text
    assert words in response.json()["detail"]
    assert localizer.calls == 0
    assert post(client, [5, 6], odometry_text([0.0, 10.0], [0.0, 0.0])).status_code == 200  # the server stays up


def test_a_gallery_without_positions_says_it_cannot_follow_a_route():
    client = TestClient(create_app(RouteLocalizer(places=False)))
    response = post(client, [5], odometry_text([0.0], [0.0]))
    assert response.status_code == 409 and "cannot follow a route" in response.json()["detail"]
