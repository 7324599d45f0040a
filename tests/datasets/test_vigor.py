"""VIGOR: the reader on hand-written folders in the released format, the tile grid against brute force, and the
synthetic vigor layout read back by the reader."""
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from geoloc.data.geo import haversine_m
from geoloc.datasets.vigor import CITIES, vigor_split
from geoloc.synthetic import MARKER, generate
from geoloc.synthetic.generate import write_marker
from geoloc.synthetic.tiles import TileGrid

# the real example line of docs/conventions.md "VIGOR split lines" (the panorama, its positive with offsets
# 23.0 -29.0, a semi-positive 20.0 300.0); the remaining two semi-positives are made up in the same form.
EXAMPLE_PANO = "L-1poX8YZAmBZVLMqBu-4w,41.877949,-87.689396,.jpg"
EXAMPLE_SATS = ["satellite_41.877971796211014_-87.68943505304125.png",
                "satellite_41.877971796211014_-87.68899446364951.png",
                "satellite_41.87764359775486_-87.68943505304125.png",
                "satellite_41.87764359775486_-87.68899446364951.png"]
EXAMPLE_LINE = (f"{EXAMPLE_PANO} {EXAMPLE_SATS[0]} 23.0 -29.0 {EXAMPLE_SATS[1]} 20.0 300.0 "
                f"{EXAMPLE_SATS[2]} -270.0 -29.0 {EXAMPLE_SATS[3]} -270.0 300.0")


def _city(root: Path, city: str, lat: float, lon: float, n_train: int, n_test: int, extra_sats: int = 1):
    """A city with 4 + extra_sats satellites; every panorama uses the first four."""
    sats = [f"satellite_{lat + i * 1e-4}_{lon}.png" for i in range(4 + extra_sats)]
    folder = root / "splits" / city
    folder.mkdir(parents=True)
    (folder / "satellite_list.txt").write_text("".join(s + "\n" for s in sats))
    lines = []
    for k in range(n_train + n_test):
        pano = f"{city}{k:03d}xxxxxxxxxxxxxxx,{lat + 1e-5 * k:.6f},{lon:.6f},.jpg"
        order = [sats[(k + j) % 4] for j in range(4)]  # the positive rotates through the first four
        lines.append(" ".join([pano] + [f"{s} 1.0 -2.0" for s in order]) + "\n")
    (folder / "same_area_balanced_train.txt").write_text("".join(lines[:n_train]))
    (folder / "same_area_balanced_test.txt").write_text("".join(lines[n_train:]))
    (folder / "pano_label_balanced.txt").write_text("".join(lines))
    return sats


@pytest.fixture
def released(tmp_path):
    root = tmp_path / "VIGOR"
    sats = {c: _city(root, c, 40.0 + i, -80.0 - i, n_train=3, n_test=2) for i, c in enumerate(CITIES)}
    return root, sats


def test_design_example_line(tmp_path):
    folder = tmp_path / "splits" / "Chicago"
    folder.mkdir(parents=True)
    (folder / "satellite_list.txt").write_text("\n".join(EXAMPLE_SATS[::-1]) + "\n")  # list order != line order
    (folder / "same_area_balanced_test.txt").write_text(EXAMPLE_LINE + "\n")
    s = vigor_split(tmp_path, "same_area", "test", cities=["Chicago"])
    assert s.name == "vigor/same_area/test" and s.num_queries == 1 and s.num_references == 4
    assert s.queries[0] == tmp_path / "Chicago" / "panorama" / EXAMPLE_PANO
    assert s.references[0] == tmp_path / "Chicago" / "satellite" / EXAMPLE_SATS[3]
    assert s.positives.tolist() == [3] and s.semi_positives.tolist() == [[2, 1, 0]]
    np.testing.assert_array_equal(s.query_latlon, [[41.877949, -87.689396]])
    assert s.reference_latlon[3].tolist() == [41.877971796211014, -87.68943505304125]
    # The offsets say the positive's centre is 23 px north and 29 px west of the panorama; at VIGOR's ~0.11 m
    # per pixel that is about 4.1 m, which the file names' GPS give too.
    assert haversine_m(s.query_latlon[0], s.reference_latlon[3]) == pytest.approx(0.111 * np.hypot(23, 29), abs=0.3)


def test_same_area_reads_every_city(released):
    root, sats = released
    train, test = vigor_split(root, "same_area", "train"), vigor_split(root, "same_area", "test")
    assert train.num_queries == 4 * 3 and test.num_queries == 4 * 2
    assert train.references == test.references  # same area: one gallery, every satellite of the four cities
    assert train.references == [root / c / "satellite" / n for c in CITIES for n in sats[c]]
    assert [q.parent.parent.name for q in test.queries] == [c for c in CITIES for _ in range(2)]
    for s in (train, test):
        names = [s.references[i].name for i in s.positives]
        # each positive lies in its query's city, and the line's positive is the one read
        assert all(s.references[i].parent.parent.name == q.parent.parent.name for i, q in zip(s.positives, s.queries))
        assert all(n.startswith("satellite_") for n in names)
        assert (s.semi_positives >= 0).all() and s.semi_positives.shape == (s.num_queries, 3)
    # train line k of a city starts with sats[k % 4], then the next three
    assert train.references[train.positives[1]].name == sats["Chicago"][1]
    assert [train.references[i].name for i in train.semi_positives[1]] == sats["Chicago"][2:4] + sats["Chicago"][:1]


def test_cross_area_cities_and_file(released):
    root, sats = released
    train, test = vigor_split(root, "cross_area", "train"), vigor_split(root, "cross_area", "test")
    assert sorted({q.parent.parent.name for q in train.queries}) == ["NewYork", "Seattle"]
    assert sorted({q.parent.parent.name for q in test.queries}) == ["Chicago", "SanFrancisco"]
    assert train.num_queries == test.num_queries == 2 * 5  # pano_label_balanced.txt: every panorama of a city
    assert {r.parent.parent.name for r in test.references} == {"Chicago", "SanFrancisco"}
    assert test.num_references == 2 * len(sats["Chicago"])
    one = vigor_split(root, "cross_area", "test", cities=["Seattle"])
    assert one.num_queries == 5 and {r.parent.parent.name for r in one.references} == {"Seattle"}


def test_another_splits_folder(released):
    root, _ = released
    (root / "splits").rename(root / "splits__corrected")
    s = vigor_split(root, "same_area", "test", splits_dir="splits__corrected")
    assert s.num_queries == 8 and s.references[0].parent == root / "Chicago" / "satellite"
    assert vigor_split(root, "same_area", "test").num_queries == 8  # splits_dir=null finds it
    with pytest.raises(FileNotFoundError, match="cities found there: \\[\\]"):
        vigor_split(root, "same_area", "test", splits_dir="splits")


def _break(root: Path, file: str, text: str):
    (root / "splits" / "Chicago" / file).write_text(text)


@pytest.mark.parametrize("setup, err, match", [
    (lambda r: (r / "splits/Chicago/same_area_balanced_test.txt").unlink(), FileNotFoundError,
     "same_area_balanced_test.txt not found"),
    (lambda r: (r / "splits/Chicago/satellite_list.txt").unlink(), FileNotFoundError, "satellite_list.txt not found"),
    (lambda r: _break(r, "same_area_balanced_test.txt", "a b c\n"), ValueError,
     r"same_area_balanced_test.txt:1: expected 13 space-separated fields .* got 3"),
    (lambda r: _break(r, "same_area_balanced_test.txt", "\n" + EXAMPLE_LINE + "\n"), ValueError,
     r"same_area_balanced_test.txt:2: satellite satellite_41.877971796211014_-87.68943505304125.png is not in"),
    (lambda r: _break(r, "same_area_balanced_test.txt", EXAMPLE_LINE.replace("23.0", "north") + "\n"), ValueError,
     r":1: field 3 should be a pixel offset, got 'north'"),
    (lambda r: _break(r, "satellite_list.txt", "satellite_1.0_2.0.png\nsatellite_1.0_2.0.png\n"), ValueError,
     r"satellite_list.txt:2: satellite satellite_1.0_2.0.png is listed again \(first on line 1\)"),
    (lambda r: _break(r, "satellite_list.txt", "sat_1.0.png\n"), ValueError,
     r"satellite_list.txt:1: satellite name 'sat_1.0.png' is not 'satellite_<lat>_<lon>.png'"),
])
def test_bad_input_names_file_and_line(released, setup, err, match):
    root, _ = released
    setup(root)
    with pytest.raises(err, match=match):
        vigor_split(root, "same_area", "test")


def test_bad_arguments_and_missing_city(released):
    root, _ = released
    with pytest.raises(ValueError, match="setting must be one of"):
        vigor_split(root, "same-area", "test")
    with pytest.raises(ValueError, match="split must be one of"):
        vigor_split(root, "same_area", "val")
    with pytest.raises(FileNotFoundError, match=r"city 'Boston'.*cities found there: \['Chicago', 'NewYork'"):
        vigor_split(root, "same_area", "test", cities=["Boston"])
    with pytest.raises(ValueError, match="without repeats"):
        vigor_split(root, "same_area", "test", cities=["Chicago", "Chicago"])
    line = EXAMPLE_LINE.replace(EXAMPLE_PANO, "no-gps.jpg")
    _city(root / "more", "Chicago", 41.0, -87.0, 0, 0)
    (root / "more/splits/Chicago/satellite_list.txt").write_text("\n".join(EXAMPLE_SATS) + "\n")
    (root / "more/splits/Chicago/same_area_balanced_test.txt").write_text(line + "\n")
    with pytest.raises(ValueError, match=r":1: panorama name 'no-gps.jpg' is not"):
        vigor_split(root / "more", "same_area", "test", cities=["Chicago"])


def test_tile_grid_against_brute_force():
    grid = TileGrid(n=4, tile_cells=96, cell=0.5)  # 48 m tiles, centres 24 m apart
    centres = np.array([grid.centre(ix, iy) for iy in range(4) for ix in range(4)])
    assert grid.number(1, 2) == 9 and tuple(centres[9]) == grid.centre(1, 2)
    rng = np.random.default_rng(0)
    for east, north in rng.uniform(-grid.half_span_m, grid.half_span_m, (300, 2)):
        held = [grid.number(*t) for t in grid.tiles_holding(east, north)]
        cheb = np.abs(centres - (east, north)).max(1)
        assert held[0] == int(np.argmin(cheb)) and cheb[held[0]] <= grid.tile_m / 4  # central quarter
        assert sorted(held) == sorted(np.flatnonzero(cheb < grid.tile_m / 2).tolist())  # all tiles holding it
    # on a centre line at the grid's edge, the neighbour that exists
    assert grid.tiles_holding(grid.half_span_m, 0.0)[1][0] == 2
    with pytest.raises(ValueError, match="outside the grid"):
        grid.tiles_holding(grid.half_span_m + 1, 0.0)


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    return generate("vigor", tmp_path_factory.mktemp("vigor") / "ds", seed=3, preset="vigor_tiny", progress=False)


def _axis_offsets(query_latlon, tile_latlon):
    """(north, east) metres from each query to its tile's centre, each measured along one axis."""
    north = haversine_m(query_latlon, np.column_stack([tile_latlon[:, 0], query_latlon[:, 1]]))
    east = haversine_m(tile_latlon, np.column_stack([tile_latlon[:, 0], query_latlon[:, 1]]))
    sign = np.sign(tile_latlon - query_latlon)
    return sign[:, 0] * north, sign[:, 1] * east


def test_synthetic_layout_reads_back(synthetic):
    marker = json.loads((synthetic / MARKER).read_text())
    assert marker["complete"] and marker["options"] == {"cities": 2, "grid": 3}
    tile_m, tile_px = 96.0, 64  # vigor_tiny: 1 m cells, 96 m tiles of 64 px
    cities = ["Chicago", "NewYork"]
    train = vigor_split(synthetic, "same_area", "train", cities=cities)
    test = vigor_split(synthetic, "same_area", "test", cities=cities)
    assert train.num_queries == 2 * 4 and test.num_queries == 2 * 3 and train.num_references == 2 * 9
    # neighbouring tile centres are half a tile apart
    assert haversine_m(train.reference_latlon[0], train.reference_latlon[1]) == pytest.approx(tile_m / 2, abs=1e-3)
    assert haversine_m(train.reference_latlon[0], train.reference_latlon[3]) == pytest.approx(tile_m / 2, abs=1e-3)
    for s in (train, test):
        n, e = _axis_offsets(s.query_latlon, s.reference_latlon[s.positives])
        assert np.abs(n).max() <= tile_m / 4 + 1e-2 and np.abs(e).max() <= tile_m / 4 + 1e-2  # central quarter
        for j in range(3):
            n, e = _axis_offsets(s.query_latlon, s.reference_latlon[s.semi_positives[:, j]])
            assert np.abs(n).max() < tile_m / 2 and np.abs(e).max() < tile_m / 2  # inside the tile
        assert all(len(set(row)) == 4 for row in np.column_stack([s.positives, s.semi_positives]).tolist())
    for q in train.queries[:2] + test.queries[:1]:
        assert cv2.imread(str(q)).shape == (64, 128, 3)
    assert all(r.is_file() for r in train.references) and cv2.imread(str(train.references[0])).shape == (64, 64, 3)
    # the written pixel offsets agree with the GPS: tile centre minus panorama, (north, east) pixels
    line = (synthetic / "splits/Chicago/same_area_balanced_train.txt").read_text().splitlines()[0].split()
    n, e = _axis_offsets(train.query_latlon[:1], train.reference_latlon[train.positives[:1]])
    px = tile_m / tile_px
    assert abs(float(line[2]) - n[0] / px) <= 0.5 and abs(float(line[3]) - e[0] / px) <= 0.5


def test_synthetic_cross_area_and_panorama_list(synthetic):
    cross = vigor_split(synthetic, "cross_area", "test", cities=["Chicago"])
    same = [vigor_split(synthetic, "same_area", sp, cities=["Chicago"]) for sp in ("train", "test")]
    assert cross.queries == same[0].queries + same[1].queries  # pano_label_balanced: train lines, then test
    with pytest.raises(FileNotFoundError, match="city 'Seattle'"):
        vigor_split(synthetic, "cross_area", "train")  # the tiny preset renders two cities only


def test_a_synthetic_tree_without_its_complete_marker_is_refused_as_an_unfinished_render(synthetic, tmp_path):
    """Without the marker, or with a render's incomplete one, the tree was read as a released VIGOR (640 px tiles,
    the cities' real scale) and fine_mean_m moved from 64.4 to 50.4 without a word."""
    marker = json.loads((synthetic / MARKER).read_text())
    cut = shutil.copytree(synthetic, tmp_path / "cut")
    (cut / MARKER).unlink()
    with pytest.raises(ValueError, match=rf"{cut} is an unfinished geoloc synthetic render \(it holds "
                                         rf"geoloc_offsets.json, .* but no complete {MARKER}\); render it again"):
        vigor_split(cut, "same_area", "test", cities=["Chicago"])
    write_marker(cut, {k: v for k, v in marker.items() if k != "complete"}, complete=False)  # killed part-way
    with pytest.raises(ValueError, match=rf"unfinished geoloc synthetic render \(its {MARKER} says the render did"):
        vigor_split(cut, "same_area", "test", cities=["Chicago"])
    (cut / "geoloc_offsets.json").unlink()  # killed before the offsets were written: the marker alone tells
    with pytest.raises(ValueError, match="unfinished geoloc synthetic render"):
        vigor_split(cut, "same_area", "test", cities=["Chicago"])
    released = shutil.copytree(synthetic, tmp_path / "released", ignore=shutil.ignore_patterns(MARKER, "geoloc_*"))
    assert vigor_split(released, "same_area", "test", cities=["Chicago"]).reference_size_px[0, 0] == 640  # as VIGOR


def test_older_layouts_keep_their_marker(tmp_path):
    """The cached default dataset stays valid: a cvusa marker has exactly the keys it had before vigor/u1652."""
    root = generate("cvusa", tmp_path / "c", 1, 0, preset="tiny", progress=False)
    marker = json.loads((root / MARKER).read_text())
    assert sorted(marker) == ["complete", "config", "generator", "layout", "preset", "seed", "train", "val", "version"]


def test_synthetic_options_are_checked(tmp_path):
    with pytest.raises(TypeError, match="'grid' belongs to layout 'vigor'"):
        generate("cvusa", tmp_path / "x", 1, 1, preset="tiny", grid=3, progress=False)
    with pytest.raises(ValueError, match=r"cities must be an integer in \[1, 4\]"):
        generate("vigor", tmp_path / "x", 1, 1, preset="vigor_tiny", cities=5, progress=False)
    assert not (tmp_path / "x").exists()


def _tree(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_synthetic_resume_and_workers_give_the_same_bytes(synthetic, tmp_path, monkeypatch):
    from geoloc.synthetic import vigor_layout

    real = vigor_layout.run

    def killed_at_job_5(*args):
        if args[5] == 5:
            raise RuntimeError("killed")
        return real(*args)

    monkeypatch.setattr(vigor_layout, "run", killed_at_job_5)
    with pytest.raises(RuntimeError, match="killed"):
        generate("vigor", tmp_path / "resumed", seed=3, preset="vigor_tiny", progress=False)
    assert not json.loads((tmp_path / "resumed" / MARKER).read_text())["complete"]
    monkeypatch.setattr(vigor_layout, "run", real)
    resumed = generate("vigor", tmp_path / "resumed", seed=3, preset="vigor_tiny", progress=False)
    assert _tree(resumed) == _tree(synthetic)
    two = generate("vigor", tmp_path / "two", seed=3, preset="vigor_tiny", workers=2, progress=False)
    assert _tree(two) == _tree(synthetic)
