"""Routes through a synthetic vigor world (geoloc/synthetic/routes.py): frames spacing_m apart along the roads, on
road cells, inside the tiles; odometry that is the truth plus the stated noise; the same bytes from the same
arguments; the refusal of an existing routes folder; the command on a tiny dataset."""
import csv
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
from geoloc.data.geo import latlon_to_offset, offset_to_latlon
from geoloc.synthetic import generate
from geoloc.synthetic.city import build_city, city_rngs
from geoloc.synthetic.classes import ROAD, ROADLINES
from geoloc.synthetic.road_graph import Stretch, drive
from geoloc.synthetic.routes import ROUTE_CODE, heading_change, main, route_positions, write_routes
from geoloc.synthetic.vigor_layout import SPLIT_CODES
from geoloc.synthetic.world_config import resolve, resolve_options

from conftest import REPO

SEED = 3
FRAMES, SPACING = 12, 10.0


@pytest.fixture(scope="module")
def world():
    cfg, _ = resolve("vigor", "vigor_tiny", {})
    return cfg, resolve_options("vigor", "vigor_tiny", {})


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return generate("vigor", tmp_path_factory.mktemp("vigor") / "ds", seed=SEED, preset="vigor_tiny", progress=False)


@pytest.fixture(scope="module")
def routes(world):
    """(city, positions, headings) of 6 routes in each city of vigor_tiny."""
    cfg, opts = world
    out = []
    for c in range(opts.cities):
        city = build_city(cfg, opts.grid, SEED, c)
        for k in range(6):
            rng = city_rngs(SEED, c, ROUTE_CODE, k, n=4)[0]
            out.append((city, *route_positions(city, rng, FRAMES, SPACING)))
    return out


def _unit(heading_deg):
    a = np.radians(heading_deg)
    return np.array([np.sin(a), np.cos(a)])


def _read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_each_step_is_spacing_metres_along_a_road(routes):
    """Brute force, step by step: either straight on (the straight line is spacing_m long, along both headings), or
    one corner between the frames: a metres along the old heading then spacing_m - a along the new one."""
    corners = 0
    for city, positions, headings in routes:
        for i in range(1, FRAMES):
            step = positions[i] - positions[i - 1]
            u, v = _unit(headings[i - 1]), _unit(headings[i])
            if np.allclose(u, v, atol=1e-9):
                assert np.linalg.norm(step) == pytest.approx(SPACING, abs=1e-6)
                assert step / SPACING == pytest.approx(u, abs=1e-6)
            else:
                a = np.dot(step - SPACING * v, u - v) / np.dot(u - v, u - v)
                assert np.allclose(a * u + (SPACING - a) * v, step, atol=1e-6)
                assert -1e-6 <= a <= SPACING + 1e-6
                corners += 1
    assert corners > 0  # the routes do turn


def test_frames_stand_on_a_road_centreline_on_road_cells(routes):
    for city, positions, _ in routes:
        segments = [(r.pts[:-1], r.pts[1:]) for r in city.place.roads]
        a, b = np.concatenate([s[0] for s in segments]), np.concatenate([s[1] for s in segments])
        for p in positions:  # the distance to the nearest centreline segment, every segment tried
            t = np.clip(np.einsum("ij,ij->i", p - a, b - a) / np.einsum("ij,ij->i", b - a, b - a), 0, 1)
            assert np.min(np.linalg.norm(a + t[:, None] * (b - a) - p, axis=1)) < 1e-6
        world = city.place.world
        cells, inside = world.cell_index(positions[:, 0], positions[:, 1])
        assert inside.all() and np.isin(world.cls.flat[cells], (ROAD, ROADLINES)).all()


def test_every_frame_lies_where_four_tiles_hold_it(routes):
    for city, positions, _ in routes:
        assert np.abs(positions).max() <= city.grid.half_span_m
        for east, north in positions:
            assert len(set(city.grid.tiles_holding(east, north))) == 4


def test_heading_change_is_clockwise_positive_in_degrees():
    headings = np.array([350.0, 10.0, 100.0, 10.0, 190.0, 10.0])
    assert heading_change(headings).tolist() == [0.0, 20.0, 90.0, -90.0, 180.0, 180.0]


def test_a_drive_turns_back_where_its_road_ends():
    pts = np.stack([np.zeros(31), np.arange(31.0)], 1)  # 30 m due north, no crossing
    path = drive([Stretch(pts, np.arange(31.0))], np.random.default_rng(0), 75.0)
    assert np.linalg.norm(np.diff(path, axis=0), axis=1).sum() == pytest.approx(75.0)
    assert np.abs(path[:, 0]).max() == 0.0 and 0.0 <= path[:, 1].min() and path[:, 1].max() <= 30.0


def test_route_streams_are_apart_from_the_panoramas():
    assert ROUTE_CODE not in SPLIT_CODES.values()
    route = city_rngs(SEED, 0, ROUTE_CODE, 0)[0].random(4)
    assert all(not np.array_equal(route, city_rngs(SEED, 0, code, 0)[0].random(4)) for code in SPLIT_CODES.values())


def test_same_arguments_give_the_same_bytes_and_routes_differ(world, tmp_path):
    cfg, opts = world
    one = write_routes(tmp_path / "one", cfg, opts, SEED, 2, frames=4)
    two = write_routes(tmp_path / "two", cfg, opts, SEED, 2, frames=4, workers=2)
    files = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file())
    assert len(files) == 1 + opts.cities * 2 * (4 + 2)
    assert files == sorted(p.relative_to(two) for p in two.rglob("*") if p.is_file())
    assert all((one / f).read_bytes() == (two / f).read_bytes() for f in files)
    first, second = one / "Chicago" / "route_0000", one / "Chicago" / "route_0001"
    assert (first / "truth.csv").read_bytes() != (second / "truth.csv").read_bytes()
    assert (first / "frame_000.jpg").read_bytes() != (second / "frame_000.jpg").read_bytes()
    record = json.loads((one / "routes.json").read_text())
    assert record["seed"] == SEED and record["count"] == 2 and record["frames"] == 4
    assert record["spacing_m"] == 10.0 and record["version"] == "1.0" and record["cities"] == ["Chicago", "NewYork"]


def test_frames_are_the_vigor_panoramas_size(world, dataset, tmp_path):
    pano = next((dataset / "Chicago" / "panorama").iterdir())
    out = write_routes(tmp_path, *world, SEED, 1, frames=2)
    frame = cv2.imread(str(out / "Chicago/route_0000/frame_001.jpg"))
    assert frame.shape == cv2.imread(str(pano)).shape == (64, 128, 3)  # vigor_tiny's sphere_height x sphere_width


def test_odometry_without_noise_is_the_truth(world, tmp_path):
    cfg, opts = world
    out = write_routes(tmp_path, cfg, opts, SEED, 3, frames=FRAMES, distance_noise=0.0, heading_noise_deg=0.0)
    for route in sorted(out.glob("*/route_*")):
        odometry, truth = _read(route / "odometry.csv"), _read(route / "truth.csv")
        assert (route / "odometry.csv").read_text().splitlines()[:2] == ["frame,distance_m,heading_change_deg",
                                                                          "0,0.0,0.0"]
        assert [int(r["frame"]) for r in odometry] == [int(r["frame"]) for r in truth] == list(range(FRAMES))
        east_north = np.array([[float(r["east_m"]), float(r["north_m"])] for r in truth])
        headings = np.array([float(r["heading_deg"]) for r in truth])
        for i in range(1, FRAMES):
            assert float(odometry[i]["distance_m"]) == SPACING
            turn = (headings[i] - headings[i - 1]) % 360.0
            turn = turn - 360.0 if turn > 180.0 else turn
            assert float(odometry[i]["heading_change_deg"]) == pytest.approx(turn, abs=1e-9)
            if abs(turn) < 1e-9:  # straight on: the straight line is the distance driven
                assert np.linalg.norm(east_north[i] - east_north[i - 1]) == pytest.approx(SPACING, abs=1e-6)
        city = route.parent.name
        origin = build_city(cfg, opts.grid, SEED, ["Chicago", "NewYork"].index(city)).origin
        latlon = np.array([[float(r["lat"]), float(r["lon"])] for r in truth])
        assert np.array_equal(latlon, offset_to_latlon(origin, east_north[:, 0], east_north[:, 1]))
        assert np.allclose(latlon_to_offset(origin, latlon), east_north, atol=1e-6)


def test_odometry_noise_is_as_stated(world, tmp_path):
    cfg, opts = world
    quiet = write_routes(tmp_path / "quiet", cfg, opts, SEED, 4, frames=FRAMES, distance_noise=0.0,
                         heading_noise_deg=0.0)
    noisy = write_routes(tmp_path / "noisy", cfg, opts, SEED, 4, frames=FRAMES, distance_noise=0.05,
                         heading_noise_deg=2.0)
    factors, errors = [], []
    for route in sorted(quiet.glob("*/route_*")):
        truth, measured = _read(route / "odometry.csv")[1:], _read(noisy / route.relative_to(quiet) / "odometry.csv")
        assert (route / "truth.csv").read_bytes() == (noisy / route.relative_to(quiet) / "truth.csv").read_bytes()
        factors += [float(m["distance_m"]) / float(t["distance_m"]) for t, m in zip(truth, measured[1:])]
        errors += [float(m["heading_change_deg"]) - float(t["heading_change_deg"])
                   for t, m in zip(truth, measured[1:])]
    factors, errors = np.array(factors), np.array(errors)
    assert len(factors) == opts.cities * 4 * (FRAMES - 1)  # 88 steps
    assert np.abs(factors - 1).max() < 5 * 0.05 and 0.7 * 0.05 < factors.std() < 1.3 * 0.05
    assert abs(factors.mean() - 1) < 3 * 0.05 / np.sqrt(len(factors))
    assert np.abs(errors).max() < 5 * 2.0 and 0.7 * 2.0 < errors.std() < 1.3 * 2.0


def test_an_existing_routes_folder_is_refused_unless_overwrite(world, tmp_path):
    cfg, opts = world
    out = write_routes(tmp_path, cfg, opts, SEED, 2, frames=2)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(ValueError, match=f"{out} is not empty.*overwrite=True"):
        write_routes(tmp_path, cfg, opts, SEED + 1, 1, frames=2)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    write_routes(tmp_path, cfg, opts, SEED, 1, frames=2, overwrite=True)
    assert not (out / "Chicago" / "route_0001").exists() and json.loads((out / "routes.json").read_text())["count"] == 1
    with pytest.raises(ValueError, match="spacing_m"):
        write_routes(tmp_path / "x", cfg, opts, SEED, 1, spacing_m=0.0)
    for frames in (1, 1001):  # a route moves; frame_NNN.jpg has three digits
        with pytest.raises(ValueError, match=r"frames must be an integer in \[2, 1000\]"):
            write_routes(tmp_path / "x", cfg, opts, SEED, 1, frames=frames)
    assert not (tmp_path / "x").exists()


def test_the_command_draws_routes_in_the_dataset_world(world, dataset, tmp_path, capsys):
    done = subprocess.run([sys.executable, "-m", "geoloc.synthetic.routes", str(dataset), "--count", "1",
                           "--frames", "3", "--preset", "vigor_tiny"], capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(dataset / "routes")
    direct = write_routes(tmp_path, *world, SEED, 1, frames=3)
    files = sorted(p.relative_to(direct) for p in direct.rglob("*") if p.is_file())
    assert all((direct / f).read_bytes() == (dataset / "routes" / f).read_bytes() for f in files)
    with pytest.raises(SystemExit) as exit_:
        main([str(dataset), "--count", "1", "--frames", "3"])
    assert exit_.value.code == 2 and "overwrite" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(dataset), "--seed", str(SEED + 1), "--overwrite"])
    assert "seed 3, not 4" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(tmp_path / "nowhere")])
    assert "holds no geoloc_synthetic.json" in capsys.readouterr().err
