"""geoloc.data.polar.street_to_ground: the grid against a brute-force ray, and a rendered panorama's ground against its tile."""
import math

import numpy as np
import pytest
from geoloc.config import ConfigError
from geoloc.data.polar import street_to_ground, street_to_ground_grid
from geoloc.launch import run
from geoloc.synthetic.classes import ROAD, ROADLINES
from geoloc.synthetic.world_config import resolve
from geoloc.synthetic.samples import render_pair
from geoloc.tasks.crossview.data_config import parse_dataset
from geoloc.tasks.crossview.datasets import read_split
from helpers.crossview_runs import train_cfg


def _band_pixel_of(east, north, height, band_hw):
    """Brute force: the unit ray from the camera to ground point (east, north, -height), its azimuth and elevation
    read off the vector, and the band pixel (col, row) that looks along it (column j: bearing 180° + 360°·j/W)."""
    ray = np.array([east, north, -height]) / math.sqrt(east**2 + north**2 + height**2)
    azimuth = math.degrees(math.atan2(ray[0], ray[1])) % 360.0
    elevation = math.degrees(math.asin(ray[2]))
    h, w = band_hw
    col = ((azimuth - 180.0) % 360.0) * w / 360.0
    row = (45.0 - elevation) * h / 90.0 - 0.5
    return col, row


@pytest.mark.parametrize("extent, height", [(72.96, 2.2), (144.0, 2.5)])
def test_grid_matches_a_brute_force_ray(extent, height):
    band, out = (64, 256), (32, 32)
    map_x, map_y = street_to_ground_grid(band, out, extent, height)
    rng = np.random.default_rng(0)
    for y, x in rng.integers(0, 32, size=(40, 2)):
        east, north = (x + 0.5 - 16) * extent / 32, (16 - y - 0.5) * extent / 32
        col, row = _band_pixel_of(east, north, height, band)
        assert map_y[y, x] == pytest.approx(row, abs=1e-3)
        assert (map_x[y, x] - col + 1) % 256 == pytest.approx(1, abs=1e-3)  # equal up to a whole turn
    assert not map_x.flags.writeable  # shared through the cache


def test_north_of_the_camera_is_up_and_the_near_ground_low_in_the_band():
    band = np.zeros((64, 256), np.uint8)
    band[:, 128] = 255  # the centre column looks north
    img = street_to_ground(band, (33, 33), 60.0, 2.0)
    lit = np.argwhere(img > 100)
    assert len(lit) and np.all(lit[:, 1] == 16) and np.all(lit[:, 0] < 16)  # straight up from the centre
    rows = np.zeros((64, 256), np.uint8)
    rows[56:] = 255  # elevations -33.75° to -45°: the ground 2.0 to 3.0 m away from a camera 2 m high
    near = street_to_ground(rows, (120, 120), 60.0, 2.0)  # 0.5 m a pixel
    d = 0.5 * np.hypot(*(np.argwhere(near > 127) + 0.5 - 60).T)
    assert len(d) > 50 and 1.7 < d.min() and d.max() < 3.3


def test_bad_arguments_say_what_is_wrong():
    with pytest.raises(ValueError, match="extent_m > 0"):
        street_to_ground_grid((8, 32), (8, 8), 0.0, 2.0)
    with pytest.raises(ValueError, match="camera_height_m > 0"):
        street_to_ground(np.zeros((8, 32, 3), np.uint8), (8, 8), 50.0, -1.0)


def test_only_full_sphere_queries_take_it(tiny_cvusa):
    """A CVUSA-style panorama's rows have no stated elevations: the dataset refuses the projection, naming the fix."""
    data, reader = parse_dataset({"name": "cvusa", "root": str(tiny_cvusa), "alignment": "ground"})
    with pytest.raises(ConfigError, match="full-sphere panorama .* use dataset.alignment=ipt"):
        read_split(data, reader, "train")
    with pytest.raises(ConfigError, match="ground_extent_m must be a finite number of metres > 0"):
        parse_dataset({"name": "vigor", "alignment": "ground", "ground_extent_m": 0})


@pytest.mark.parametrize("key", ["ground_extent_m", "camera_height_m"])
def test_a_ground_scale_that_is_not_a_finite_positive_number_is_refused_before_the_run_claims_its_folder(
        key, tiny_cvusa, tmp_path):
    """inf passed the parse: the run claimed its folder, died at its first item, and the corrected run was refused."""
    for value in ("inf", "nan", "0", "-2.5"):
        with pytest.raises(ConfigError, match=rf"dataset.{key} must be a finite number of metres > 0.*got {value}"):
            parse_dataset({"name": "vigor", "alignment": "ground", key: float(value)})
    run_dir = tmp_path / "run"
    with pytest.raises(ConfigError, match=rf"dataset.{key} must be a finite number"):
        run.train(train_cfg(tiny_cvusa, run_dir, "dataset.alignment=ground", f"dataset.{key}=inf"))
    assert not run_dir.exists()


def test_a_rendered_panorama_projects_its_road_onto_the_tile_road():
    """The synthetic cvact layout (camera at the tile's centre, its pose jittered by up to 2 m and 10°): the road the
    band shows, projected onto the ground within 20 m, lies on the tile's road; turned by a quarter or mirrored, it
    does not (the test can fail)."""
    cfg, _ = resolve("cvact", "tiny", dict(aerial_size=128, sphere_height=128, sphere_width=256, cell_m=0.5,
                                           tile_m=96.0))
    yy, xx = np.mgrid[:128, :128]
    near = np.hypot(yy - 63.5, xx - 63.5) * cfg.tile_m / 128 < 20.0
    hits, turned, mirrored = [], [], []
    for i in range(6):
        out = render_pair(cfg, 0, "val", i, sphere=True)
        band = out["pano_labels"][32:96]  # the horizon band, +45° to -45°
        road = np.isin(band, (ROAD, ROADLINES)).astype(np.uint8) * 255
        projected = (street_to_ground(road, (128, 128), cfg.tile_m, cfg.camera_height) > 127) & near
        truth = np.isin(out["aerial_labels"], (ROAD, ROADLINES))
        assert projected.sum() > 200
        hits.append(truth[projected].mean())
        turned.append(np.rot90(truth)[projected].mean())
        mirrored.append(truth[:, ::-1][projected].mean())
    assert min(hits) > 0.8, hits
    assert max(turned) < 0.2, turned
    assert np.mean(mirrored) < np.mean(hits) - 0.3, (hits, mirrored)
