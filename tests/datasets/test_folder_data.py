"""dataset=folder (your own data): positives, radius relevance, tile positions and the area split against brute force;
VPR file names; relevance and recall against VPR-methods-evaluation's rules (helpers/vpr_reference.py); every
refusal names the file, the line and what to do."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest
from geoloc.config import ConfigError
from geoloc.data.geo import haversine_m, offset_to_latlon
from geoloc.datasets.folder import folder

from helpers.own_data import ORIGIN, grid, positions_csv, write_folder
from helpers.vpr_reference import reference_east_north, reference_positives, reference_recalls

TILES = grid(4, 3, 50.0)  # 12 tiles, 50 m apart
QUERIES = TILES[[0, 1, 2, 3, 5, 6, 9, 11]] + np.array(
    [[3, -2], [10, 4], [-7, 1], [0, 0], [12, -9], [-3, 14], [6, 6], [-11, -2]], np.float64)


@pytest.fixture
def own(tmp_path):
    return write_folder(tmp_path / "own", TILES, QUERIES, aerial=20, pano=(8, 32))


def test_positives_relevance_and_tile_positions_match_brute_force(own):
    split = folder(str(own), "all", tile_extent_m=40.0, radius_m=40.0)
    q, t = split.query_latlon, split.reference_latlon
    d = haversine_m(q[:, None], t[None])
    assert split.positives.tolist() == d.argmin(1).tolist()
    relevant = [sorted(r[r >= 0].tolist()) for r in split.relevance.relevant]
    assert relevant == [sorted(np.flatnonzero(row <= 40.0).tolist()) for row in d]
    assert any(len(r) > 1 for r in relevant)  # the radius adds neighbours: the test can tell the rules apart
    assert np.allclose(split.reference_metres_per_px, 2.0) and (split.reference_size_px == 20).all()
    offset = QUERIES - TILES[split.positives]  # (east, north) from the tile centre, 2 m per pixel
    assert np.allclose(split.query_tile_px, np.column_stack([10 - offset[:, 1] / 2, 10 + offset[:, 0] / 2]), atol=1e-3)
    assert np.allclose(split.query_tile_offset_m(), offset, atol=2e-3)
    same = folder(str(write_folder(own.parent / "xy", TILES, QUERIES, aerial=20, pano=(8, 32), system="xy")),
                  "all", metres_per_px=2.0, radius_m=40.0)
    assert same.positives.tolist() == split.positives.tolist() and np.allclose(same.query_tile_px, split.query_tile_px, atol=1e-3)


@pytest.mark.parametrize("axis", ["east", "north"])
def test_the_split_is_by_area_and_deterministic(own, axis):
    whole = folder(str(own), "all", tile_extent_m=40.0)
    train = folder(str(own), "train", tile_extent_m=40.0, split_axis=axis, test_fraction=0.4)
    test = folder(str(own), "test", tile_extent_m=40.0, split_axis=axis, test_fraction=0.4)
    assert set(train.references).isdisjoint(test.references) and set(train.queries).isdisjoint(test.queries)
    assert sorted(train.references + test.references) == sorted(whole.references)
    assert sorted(train.queries + test.queries) == sorted(whole.queries)
    k = 0 if axis == "east" else 1
    coordinate = {p: TILES[i, k] for i, p in enumerate(whole.references)}
    line = np.quantile(TILES[:, k], 0.6)
    assert all(coordinate[p] >= line for p in test.references) and all(coordinate[p] < line for p in train.references)
    nearest = {whole.queries[i]: whole.references[p] for i, p in enumerate(whole.positives)}
    for part in (train, test):  # a query goes where its nearest tile is, and that tile is its positive
        assert all(nearest[query] == part.references[p] for query, p in zip(part.queries, part.positives))
    assert f"{axis} >= " in test.name and folder(str(own), "test", tile_extent_m=40.0, split_axis=axis,
                                                  test_fraction=0.4).queries == test.queries


FIJI = (-16.5, 179.9995)  # 53 m west of the 180° meridian: a grid around it lies on both sides


def test_a_folder_across_the_180_meridian_reads_as_the_same_folder_elsewhere(tmp_path):
    """Tiles and queries either side of the meridian (a query 15 m from its tile was refused as outside it, and the
    area split was drawn in a frame broken at the meridian): positives, tile positions, the split and its line are
    those of the same layout around ORIGIN."""
    tiles = TILES - [50.0, 0.0]  # east -50 to 100 m: the meridian lies 53 m east of FIJI
    queries = tiles + [15.0, 0.0]
    far, near = (write_folder(tmp_path / name, tiles, queries, aerial=20, pano=(8, 32), origin=origin)
                 for name, origin in (("far", ORIGIN), ("near", FIJI)))
    lons = np.loadtxt(near / "tiles.csv", delimiter=",", skiprows=1, usecols=2)
    assert (lons > 179.99).any() and (lons < -179.99).any()  # both sides, each in [-180, 180]
    for split in ("all", "train", "test"):
        one, other = (folder(str(root), split, tile_extent_m=40.0, relevance="nearest_tile", test_fraction=0.5)
                      for root in (far, near))
        assert one.name == other.name and [p.name for p in one.references] == [p.name for p in other.references]
        assert [p.name for p in one.queries] == [p.name for p in other.queries]
        assert other.positives.tolist() == one.positives.tolist()
        np.testing.assert_allclose(other.query_tile_px, one.query_tile_px, atol=1e-3)
        np.testing.assert_allclose(other.query_tile_px[:, 1], 10 + 15.0 / 2, atol=1e-3)  # 15 m east, 2 m a pixel


def vpr_name(east, north, zone=32, letter="U", k=0):
    lat, lon = offset_to_latlon(ORIGIN, east, north)
    return f"@{500000 + east:.2f}@{5400000 + north:.2f}@{zone}@{letter}@{lat:.5f}@{lon:.5f}@pano{k}@@@@@@@@.jpg"


def test_vpr_file_names_need_no_csv_and_one_utm_zone(own):
    for side, positions in (("tiles", TILES), ("queries", QUERIES)):
        (own / f"{side}.csv").unlink()
        for i, old in enumerate(sorted((own / side).iterdir())):
            old.rename(own / side / vpr_name(*positions[i], k=i))
    split = folder(str(own), "all", tile_extent_m=40.0)
    assert split.query_xy is not None and split.query_latlon is None
    k = [int(p.name.split("@")[7][4:]) for p in split.queries]  # pano<k>: the query's row in QUERIES
    assert np.allclose(split.query_xy - split.reference_xy[split.positives], QUERIES[k] - TILES[[0, 1, 2, 3, 5, 6, 9, 11]][k])
    odd = next((own / "tiles").iterdir())
    odd.rename(own / "tiles" / vpr_name(0, 0, zone=33, k=99))
    with pytest.raises(ValueError, match=r"UTM zone 33U differs from 32U .*give positions in one zone, or as lat,lon"):
        folder(str(own), "all", tile_extent_m=40.0)
    odd = own / "tiles" / vpr_name(0, 0, zone=33, k=99)
    odd.rename(own / "tiles" / "plain.jpg")
    with pytest.raises(ValueError, match=r"plain.jpg' is not a VPR name .*Write .*tiles.csv"):
        folder(str(own), "all", tile_extent_m=40.0)


def test_a_file_name_that_is_not_utf8_is_refused_when_the_folder_is_read(own):
    """A Latin-1 name passed the reader, then `gallery.save=` died after encoding with a bare UnicodeEncodeError."""
    for side, positions in (("tiles", TILES), ("queries", QUERIES)):
        name_as(own, side, [vpr_name(*p, k=i) for i, p in enumerate(positions)])
    odd = sorted((own / "tiles").iterdir())[0]
    raw = os.fsencode(odd.name).replace(b"pano0", b"caf\xe9")  # é in Latin-1: not UTF-8
    os.rename(odd, os.path.join(os.fsencode(own / "tiles"), raw))
    with pytest.raises(ValueError, match=re.escape(f"{own / 'tiles'}: the file name {raw!r} is not UTF-8")):
        folder(str(own), "all", tile_extent_m=40.0)
    (own / "tiles" / os.fsdecode(raw)).rename(own / "tiles" / vpr_name(*TILES[0], k=0).replace("pano0", "café"))
    assert folder(str(own), "all", tile_extent_m=40.0).num_references == len(TILES)  # the same name in UTF-8 reads


def name_as(own, side, names):
    (own / f"{side}.csv").unlink(missing_ok=True)
    for old, new in zip(sorted((own / side).iterdir()), names):
        old.rename(own / side / new)


def test_minimal_vpr_names_read_and_zones_must_share_a_frame(own):
    name_as(own, "queries", [f"@{500000 + e:.2f}@{5400000 + n:.2f}@.jpg" for e, n in QUERIES])  # no zone
    name_as(own, "tiles", [vpr_name(*p, letter="T" if i % 2 else "U", k=i) for i, p in enumerate(TILES)])
    split = folder(str(own), "all", tile_extent_m=45.0)  # 32T and 32U: one zone, two latitude bands
    read = split.query_xy[np.lexsort(split.query_xy.T)]  # files in name order; compare as sets of positions
    want = QUERIES + [500000, 5400000]
    assert np.allclose(read, want[np.lexsort(want.T)]) and split.num_references == len(TILES)
    first = sorted((own / "queries").iterdir())[0]
    first.rename(first.with_name(first.name.replace("@.jpg", "@33@@.jpg")))
    with pytest.raises(ValueError, match=r"queries is in UTM zone 33 and .*tiles in 32[TU]: give both in one zone"):
        folder(str(own), "all", tile_extent_m=45.0)


def write_table(own, side, text):
    (own / f"{side}.csv").write_text(text)


ROWS = positions_csv([f"t{i:03d}.png" for i in range(12)], TILES).splitlines(keepends=True)


@pytest.mark.parametrize("rows, message", [
    (ROWS[:3] + ["t002.png,48.8,north\n"] + ROWS[4:], r"tiles.csv:4: lat,lon must be numbers, got '48.8','north'"),
    (ROWS[:5] + ["t004.png,48.8\n"] + ROWS[6:], r"tiles.csv:6: 2 fields, the header has 3"),
    (["image,lat,lon,altitude\n"] + ROWS[1:], r"tiles.csv:1: header .*unknown column 'altitude'. The header is one of"),
    (["image,lat,lon,east_m,north_m\n"] + ROWS[1:], r"both lat/lon and east_m/north_m columns"),
    (ROWS[:2] + ["t001.png,5400123.0,500321.0\n"] + ROWS[3:], r"tiles.csv:3: lat,lon = 5400123.0,500321.0 is not a "
                                                             r"position in degrees .*header image,east_m,north_m"),
    (ROWS[:2] + ["t999.png,48.8,2.3\n"] + ROWS[3:], r"tiles.csv:3: image t999.png not found in .*fix the name or "
                                                    r"remove the row"),
    (ROWS + [ROWS[2]], r"tiles.csv:14: image t001.png is listed again \(first on line 3\)"),
    (ROWS[:-1], r"t011.png is in .*tiles but not in .*tiles.csv \(1 such images\): add a row"),
    (["image,east_m,north_m,utm_zone\n", "t000.png,1,2,32T\n", "t001.png,5,2,33T\n"],
     r"tiles.csv:3: UTM zone 33T differs from 32T \(.*tiles.csv:2\)"),
])
def test_a_bad_table_is_refused_naming_the_file_and_line(own, rows, message):
    write_table(own, "tiles", "".join(rows))
    with pytest.raises((ValueError, FileNotFoundError), match=message):
        folder(str(own), "all", tile_extent_m=40.0)


def test_mixed_systems_missing_scale_and_a_query_outside_every_tile_are_refused(own):
    names = [f"q{i:03d}.png" for i in range(len(QUERIES))]
    write_table(own, "queries", positions_csv(names, QUERIES, "xy"))
    with pytest.raises(ValueError, match=r"queries.csv gives east_m,north_m \(metres\) and .*tiles.csv gives lat,lon"):
        folder(str(own), "all", tile_extent_m=40.0)
    write_table(own, "queries", positions_csv(names, QUERIES))
    with pytest.raises(ConfigError, match="needs the tiles' ground scale, one of dataset.tile_extent_m"):
        folder(str(own), "all")
    with pytest.raises(ConfigError, match="needs the tiles' ground scale"):
        folder(str(own), "all", tile_extent_m=40.0, metres_per_px=2.0)
    far = QUERIES.copy()
    far[4] = TILES[5] + [22.0, 0.0]  # 22 m east of a 30 m wide tile's centre; the next tile is 28 m away
    write_table(own, "queries", positions_csv(names, far))
    with pytest.raises(ValueError, match=r"queries.csv:6: query .*q004.png lies 22.0 m from its nearest tile's "
                                         r"centre .*t005.png\), outside that tile \(30.0 x 30.0 m\)"):
        folder(str(own), "all", tile_extent_m=30.0, relevance="nearest_tile")  # that rule keeps today's refusal
    assert folder(str(own), "all", tile_extent_m=45.0, relevance="nearest_tile").num_queries == len(QUERIES)
    with pytest.raises(ConfigError, match=r"relevance must be one of \['radius', 'nearest_tile'\].*got 'nearest'"):
        folder(str(own), "all", tile_extent_m=45.0, relevance="nearest")
    with pytest.raises(ConfigError, match="radius_m must be a finite number of metres >= 0, got -1"):
        folder(str(own), "all", tile_extent_m=45.0, radius_m=-1)


def test_the_radius_rule_keeps_a_test_query_no_tile_shows_and_training_refuses_it(own):
    far = QUERIES.copy()
    far[4] = TILES[5] + [22.0, 0.0]  # outside its 30 m tile, 22 m from its centre: in the training area
    far[7] = TILES[11] + [0.0, 40.0]  # outside its tile and 40 m from it, past the radius: in the test area
    write_table(own, "queries", positions_csv([f"q{i:03d}.png" for i in range(len(QUERIES))], far))
    whole = folder(str(own), "all", tile_extent_m=30.0)
    assert whole.num_queries == len(QUERIES) and np.isnan(whole.query_tile_px[[4, 7]]).all()
    assert not np.isnan(np.delete(whole.query_tile_px, [4, 7], axis=0)).any()
    relevant = [sorted(r[r >= 0].tolist()) for r in whole.relevance.relevant]
    assert relevant[4] == [5] and relevant[7] == []  # 22 m: its tile; nothing within 25 m of the other
    test = folder(str(own), "test", tile_extent_m=30.0)
    kept = [q.name for q in test.queries].index("q007.png")
    assert np.isnan(test.query_tile_px[kept]).all() and not test.relevance.has_relevant[kept]
    with pytest.raises(ValueError, match=r"q004.png lies 22.0 m .*no tile shows it \(1 such queries\). split=train "
                                         r"pairs each query with a tile that shows it"):
        folder(str(own), "train", tile_extent_m=30.0)


def test_under_the_default_config_a_tile_24_9_m_away_is_relevant_and_one_25_1_m_away_is_not(tmp_path):
    from conftest import compose_train
    from helpers.crossview_runs import split_of

    tiles = np.array([[24.9, 0.0], [0.0, -25.1], [-90.0, 0.0], [90.0, 0.0]])
    root = write_folder(tmp_path / "own", tiles, np.array([[0.0, 0.0], [90.0, 5.0]]), aerial=20, system="xy")
    cfg = compose_train(["dataset=folder", f"dataset.root={root}", "dataset.tile_extent_m=60"])
    split = split_of(cfg.dataset, "all")  # no radius and no relevance given: the defaults decide
    assert [sorted(r[r >= 0].tolist()) for r in split.relevance.relevant] == [[0], [3]]
    assert split.positives.tolist() == [0, 3]
    far = write_folder(tmp_path / "far", tiles[1:], np.array([[0.0, 0.0]]), aerial=20, system="xy")
    alone = split_of({**cfg.dataset, "root": str(far)}, "all")  # its nearest tile is 25.1 m away
    assert alone.positives.tolist() == [0] and not alone.relevance.has_relevant.any()


def test_recall_agrees_with_the_reference_where_some_queries_have_no_tile_within_25_m(tmp_path):
    from geoloc.eval.retrieval_metrics import split_metrics

    queries = np.concatenate([TILES[:6] + [[3, -4], [-20, 12], [24, 7], [0, 25], [-9, -9], [17, 18]],
                              TILES[6:] + [[0, 26], [30, 0], [-25.5, 0], [18, 18], [40, 40], [1, 1]]])
    root = tmp_path / "own"
    write_folder(root, TILES, queries, aerial=20)
    for side, positions in (("queries", queries), ("tiles", TILES)):  # VPR names, which the reference reads too
        name_as(root, side, [f"@{500000 + e:.3f}@{5400000 + n:.3f}@.jpg" for e, n in positions])
    split = folder(str(root), "all", tile_extent_m=80.0)
    utm = [np.array([reference_east_north(str(p)) for p in paths]) for paths in (split.queries, split.references)]
    positives = reference_positives(*utm)
    assert sum(not p for p in positives) >= 4 and sum(len(p) > 1 for p in positives) >= 1  # misses, and neighbours
    rng = np.random.default_rng(0)
    reference = rng.normal(size=(len(TILES), 16))
    query = reference[[min(p) if p else 0 for p in positives]] + 2.0 * rng.normal(size=(len(queries), 16))
    query, reference = (x / np.linalg.norm(x, axis=1, keepdims=True) for x in (query, reference))
    ks = (1, 2, 5, 12, 20)  # K = N and K > N: a query with no positive is still a miss
    got = split_metrics(query, reference, split, ks)
    want = reference_recalls(query, reference, positives, ks)
    assert {k: got[k] for k in want} == pytest.approx(want, abs=1e-12)
    found_at_all = np.mean([bool(p) for p in positives])  # the queries with a positive: R@K's ceiling
    assert got["R@20"] == pytest.approx(found_at_all) and 0.0 < got["R@1"] < found_at_all < 1.0
    nearest = folder(str(root), "all", tile_extent_m=80.0, relevance="nearest_tile")  # every query finds a tile
    assert split_metrics(query, reference, nearest, ks)["R@20"] == 1.0


def test_the_reader_is_registered_with_its_keys(own):
    from helpers.crossview_runs import split_of

    split = split_of({"name": "folder", "root": str(own), "tile_extent_m": 40.0, "check_files": "exists"}, "test")
    assert split.name.startswith("folder/test (east >= ") and split.relevance.kind == "radius"
    with pytest.raises(ConfigError, match=re.escape("dataset.root=DIR holding queries/ and tiles/")):
        split_of({"name": "folder", "tile_extent_m": 40.0}, "test")
