"""localize.py with odometry=: a folder of frames fused into a track (route.jsonl, route.png), the filter's plane of
a gallery whose tiles lie in places far apart, and the refusals before any frame is answered."""

from __future__ import annotations

import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
from geoloc.apps.localize.route import RoutePlane, regions_of, truth_of
from geoloc.config import ConfigError
from geoloc.data.geo import haversine_m, offset_to_latlon
from geoloc.sequence.extent import GalleryExtent, RegionsExtent
from geoloc.sequence.odometry import odometry_text
from hydra import compose, initialize_config_dir

from conftest import CONF
from test_localize import gallery  # noqa: F401  (the module's trained checkpoint and saved gallery)

CHICAGO, SEATTLE = (41.8781, -87.6298), (47.6062, -122.3321)


def two_cities(step_m: float = 36.0, side: int = 4) -> np.ndarray:
    """(2 side^2, 2) tile centres (lat, lon): a side x side grid, step_m apart, in each of two cities."""
    grid = np.array([(e, n) for e in range(side) for n in range(side)], np.float64) * step_m
    return np.concatenate([offset_to_latlon(city, grid[:, 0], grid[:, 1]) for city in (CHICAGO, SEATTLE)])


def test_tiles_of_two_cities_are_two_regions_side_by_side_with_their_own_metres():
    tiles = two_cities()
    assert regions_of(tiles, 720.0).tolist() == [0] * 16 + [1] * 16
    plane = RoutePlane.of("latlon", tiles, 72.0)
    assert len(plane.extent.boxes) == 2
    # metres within a region are the ground's: neighbours 36 m apart on the plane as on the earth
    assert np.linalg.norm(plane.tiles[1] - plane.tiles[0]) == pytest.approx(haversine_m(tiles[1], tiles[0]), abs=0.01)
    # the regions far apart on the plane, and the prior's area the two boxes' only
    assert plane.tiles[16:, 0].min() - plane.tiles[:16, 0].max() > 50_000
    assert plane.extent.area_m2 == pytest.approx(2 * (3 * 36.0 + 72.0) ** 2, rel=1e-4)  # tangent planes
    for row in (0, 5, 21, 31):  # to the plane and back, in either region
        back = plane.from_plane(plane.to_plane(tiles[row], row))
        assert haversine_m(back, tiles[row]) < 1e-3
        assert np.allclose(plane.to_plane(tiles[row]), plane.tiles[row], atol=1e-6)  # its region found without row


def test_a_regions_extent_is_its_boxes():
    boxes = [GalleryExtent(0, 10, 0, 10), GalleryExtent(100, 120, 0, 5)]
    extent = RegionsExtent(boxes)
    assert extent.area_m2 == 200.0
    assert extent.contains(np.array([[5, 5], [50, 5], [110, 2], [110, 6]])).tolist() == [True, False, True, False]
    with pytest.raises(ValueError, match="at least one box"):
        RegionsExtent([])


def test_a_frame_answer_takes_the_refined_positions_and_their_confidence():
    tiles = two_cities()
    plane = RoutePlane.of("latlon", tiles, 72.0)
    near = offset_to_latlon(tiles[5], 3.0, -4.0)
    hits = [{"row": 5, "score": 0.9, "refined_position": {"lat": near[0], "lon": near[1], "mass_5m": 0.3,
                                                          "confidence_within_5m": 0.7}},
            {"row": 20, "score": 0.8, "refined_position": {"lat": tiles[20][0], "lon": tiles[20][1],
                                                           "mass_5m": 0.4}}]
    answer = plane.answer(SimpleNamespace(topk=hits))
    assert np.allclose(answer.centres, plane.tiles[[5, 20]])
    assert np.allclose(answer.refined[0] - plane.tiles[5], [3.0, -4.0], atol=0.01)
    assert answer.refined_confidence.tolist() == [0.7, 0.4]  # calibrated where given, else the refiner's own mass
    plain = plane.answer(SimpleNamespace(topk=[{"row": 5, "score": 0.9}, {"row": 6, "score": 0.5}]))
    assert plain.refined is None and plain.scores.tolist() == [0.9, 0.5]


def test_truth_csv_beside_the_frames_is_read_onto_the_plane(tmp_path):
    tiles = two_cities()
    plane = RoutePlane.of("latlon", tiles, 72.0)
    (tmp_path / "truth.csv").write_text("frame,lat,lon\n" + "".join(
        f"{i},{float(tiles[r][0])!r},{float(tiles[r][1])!r}\n" for i, r in enumerate((3, 19))))
    assert np.allclose(truth_of(tmp_path, plane), plane.tiles[[3, 19]], atol=1e-6)
    assert truth_of(tmp_path / "nowhere", plane) is None


def route_cfg(ckpt, folder, frames, out, *extra):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("localize", overrides=[f"ckpt={ckpt}", f"gallery={folder}", f"image={frames}", "topk=3",
                                              f"out={out}", "device=cpu", "heading=0", *extra])


def test_localize_py_fuses_a_folder_of_frames_with_its_odometry_into_a_track(gallery, tmp_path, capsys):  # noqa: F811
    from geoloc.apps.localize.command import localize

    root, ckpt, folder = gallery
    frames = tmp_path / "frames"
    frames.mkdir()
    for i, n in enumerate((13, 14, 15)):
        shutil.copy(root / f"streetview/panos/{n:07d}.jpg", frames / f"frame_{i:03d}.jpg")
    (frames / "odometry.csv").write_text(odometry_text([0.0, 10.0, 10.0], [0.0, 0.0, 5.0]))
    answers = localize(route_cfg(ckpt, folder, frames, tmp_path / "out", f"odometry={frames / 'odometry.csv'}",
                                 "route.particles=500"))
    lines = [json.loads(line) for line in (tmp_path / "out" / "route.jsonl").read_text().splitlines()]
    assert [line["frame"] for line in lines] == ["frame_000.jpg", "frame_001.jpg", "frame_002.jpg"]
    assert len(answers) == 3 and (tmp_path / "out" / "route.png").stat().st_size > 0
    for line in lines:
        assert set(line["position"]) == {"x_m", "y_m"} and 0.0 <= line["heading_deg"] < 360.0
        cov = np.array(line["covariance_m2"])
        assert cov.shape == (2, 2) and np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() >= -1e-6
        assert 0.0 <= line["tracked_mass"] <= 1.0 and line["region_95_area_m2"] > 0
    again = tmp_path / "again"
    localize(route_cfg(ckpt, folder, frames, again, f"odometry={frames / 'odometry.csv'}", "route.particles=500",
                       "picture=false"))
    assert [json.loads(x) for x in (again / "route.jsonl").read_text().splitlines()] == lines  # the same track
    (frames / "odometry.csv").write_text(odometry_text([0.0, 10.0], [0.0, 0.0]))
    with pytest.raises(ConfigError, match="2 rows for 3 frames"):
        localize(route_cfg(ckpt, folder, frames, tmp_path / "short", f"odometry={frames / 'odometry.csv'}"))
    assert not (tmp_path / "short").exists()  # refused before the run took its folder
    with pytest.raises(ConfigError, match="odometry="):
        localize(route_cfg(ckpt, folder, frames, tmp_path / "none", f"odometry={frames / 'missing.csv'}"))


def test_fit_route_filter_answers_every_held_out_query_on_the_route_plane(gallery, capsys):  # noqa: F811
    """tools/fit_route_filter.py: each line of the gallery's queries.jsonl answered, its truth on the filter's plane
    (x/y metres as positions.csv gives them), and the printed overrides those of fit_answer_model."""
    import importlib.util

    from conftest import REPO
    from geoloc.apps.localize.localizer import Localizer
    from geoloc.apps.localize.route import route_plane
    from geoloc.sequence.fit import fit_answer_model
    from geoloc.sequence.particle_filter import FilterConfig

    spec = importlib.util.spec_from_file_location("fit_route_filter", REPO / "tools" / "fit_route_filter.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    _, ckpt, folder = gallery
    lines = [json.loads(line) for line in (folder / "queries.jsonl").read_text().splitlines()]
    localizer = Localizer.load(str(ckpt), str(folder), device="cpu")
    answers, truths = tool.held_out_answers(localizer, route_plane(localizer.places, FilterConfig()), 3, None)
    assert len(answers) == len(lines) == 8 and all(len(a) == 3 for a in answers)
    assert np.allclose(truths, [[q["x_m"], q["y_m"]] for q in lines])
    # a radius that makes about half the answers hits: the nearest tile's distance, at its median over the answers
    radius = float(np.median([np.linalg.norm(a.centres - t, axis=1).min() for a, t in zip(answers, truths)])) + 1e-6
    args = [str(ckpt), str(folder), "--topk", "3", "--radius", str(radius), "--out", str(folder.parent / "fit.json")]
    try:
        model = fit_answer_model(answers, truths, radius_m=radius)
    except ValueError as refused:  # a one-epoch model's scores may not rank the tiles: the tool refuses alike
        with pytest.raises(ValueError, match=str(refused).split(" (")[0][:40]):
            tool.main(args)
        return
    tool.main(args)
    assert capsys.readouterr().out.strip() == (f"route.wrong_answer_prob={model.wrong_answer_prob:.4f} "
                                               f"route.temperature={model.temperature:.4f}")
    assert json.loads((folder.parent / "fit.json").read_text())["hits"] == model.hits


def load_tool(name: str):
    import importlib.util

    from conftest import REPO

    spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    return tool


def write_routes(root, folder, groups=("A", "B"), count=10) -> dict:
    """folder/<group>/route_NNNN: two frames each, the gallery's split panorama 13 + (k mod 8) standing still (zero
    odometry), truth.csv its x/y from positions.csv; -> {route folder: truth (x, y)}."""
    table = {row.split(",")[0]: row.split(",")[1:] for row in (root / "positions.csv").read_text().splitlines()[1:]}
    truths = {}
    for group in groups:
        for k in range(count):
            route = folder / group / f"route_{k:04d}"
            route.mkdir(parents=True)
            name = f"streetview/panos/{13 + k % 8:07d}.jpg"
            for i in range(2):
                shutil.copy(root / name, route / f"frame_{i:03d}.jpg")
            (route / "odometry.csv").write_text(odometry_text([0.0, 0.0], [0.0, 0.0]))
            x, y = (float(v) for v in table[name])
            (route / "truth.csv").write_text(f"frame,x_m,y_m\n0,{x!r},{y!r}\n1,{x!r},{y!r}\n")
            truths[route] = np.array([x, y])
    return truths


def test_evaluate_routes_scores_the_selected_routes_as_their_frames_are_answered(gallery, tmp_path,  # noqa: F811
                                                                                 capsys):
    from geoloc.apps.localize.localizer import Localizer
    from geoloc.apps.localize.route_cases import filter_config, parse_ids, route_folders

    root, ckpt, folder = gallery
    truths = write_routes(root, tmp_path / "routes")
    assert parse_ids("0-2,5") == [0, 1, 2, 5]
    with pytest.raises(ValueError, match="ranges like"):
        parse_ids("3-1")
    picked = route_folders(tmp_path / "routes", [1, 7])
    assert [f"{p.parent.name}/{p.name}" for p in picked] == ["A/route_0001", "A/route_0007", "B/route_0001",
                                                             "B/route_0007"]
    with pytest.raises(FileNotFoundError, match="no <group>/route_NNNN"):
        route_folders(tmp_path / "routes", [99])
    with pytest.raises(ValueError, match="route.KEY=VALUE"):
        filter_config(["route.no_such_key=1"])
    assert filter_config(["route.particles=300", "route.tile_sigma_m=30"]).particles == 300
    out = tmp_path / "scores.json"
    # the settings may follow the options, as in localize.py's command lines
    load_tool("evaluate_routes").main([str(ckpt), str(folder), str(tmp_path / "routes"), "--ids", "0-1", "--topk",
                                       "3", "route.particles=300", "--heading", "0", "--out", str(out)])
    record = json.loads(out.read_text())
    assert record["scores"]["routes"] == 4 and record["route"]["particles"] == 300
    # the single-frame share, brute force: each frame's own answer (refined or top-1 tile) within 25 m of its truth
    localizer = Localizer.load(str(ckpt), str(folder), device="cpu")
    query = localizer.parse(topk=3, heading=0.0)
    near = []
    for route in route_folders(tmp_path / "routes", [0, 1]):
        for frame in sorted(route.glob("frame_*.jpg")):
            from geoloc.data.io import read_rgb

            result = localizer.localize(read_rgb(frame), query)
            own = result.refined_position or result.position
            near.append(np.hypot(own["x_m"] - truths[route][0], own["y_m"] - truths[route][1]) <= 25.0)
    assert record["scores"]["single"] == pytest.approx(np.mean(near))
    assert "| routes |" in capsys.readouterr().out


def test_fit_route_filter_chooses_the_settings_on_the_held_out_routes(gallery, tmp_path, capsys):  # noqa: F811
    root, ckpt, folder = gallery
    write_routes(root, tmp_path / "routes")
    tool = load_tool("fit_route_filter")
    with pytest.raises(SystemExit):
        tool.main([str(ckpt), str(folder), "--routes", str(tmp_path / "routes")])  # no held-out numbers
    capsys.readouterr()
    out = tmp_path / "fit.json"
    # the temperature given (a one-epoch model's scores need not rank the tiles), q from the queries, the grid tried
    tool.main([str(ckpt), str(folder), "route.particles=300", "route.temperature=1.0", "--topk", "3", "--radius",
               "600", "--routes", str(tmp_path / "routes"), "--ids", "0-9", "--grid", "wrong_answer_prob=0.5,0.9",
               "tile_sigma_m=25,40", "--out", str(out)])
    record = json.loads(out.read_text())
    tried = record["route_scores"]
    assert [(t["wrong_answer_prob"], t["tile_sigma_m"]) for t in tried] == [(0.5, 25.0), (0.5, 40.0), (0.9, 25.0),
                                                                         (0.9, 40.0)]
    assert all(t["routes"] == 20 for t in tried)
    calibrated = [t for t in tried if t["region"] >= 0.95]
    assert record["route_calibrated"] == bool(calibrated)
    if calibrated:  # the tightest calibrated region
        best = min(t["region_ha"] for t in calibrated)
        assert any(t["region_ha"] == best and all(t[k] == v for k, v in record["route_settings"].items())
                   for t in calibrated)
    assert record["temperature"] == 1.0 and record["answers"] == 8
    printed = capsys.readouterr().out.strip()
    assert printed.startswith(f"route.wrong_answer_prob={record['route_settings']['wrong_answer_prob']:.4f} "
                              "route.temperature=1.0000 ")
    assert printed.endswith(f"route.tile_sigma_m={record['route_settings']['tile_sigma_m']:g}")
