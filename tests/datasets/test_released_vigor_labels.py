"""The VIGOR reader against released files: SliceMatch's corrected labels (real lines in tests/fixtures/released,
the whole files where GEOLOC_VIGOR_LABELS names them), read as the field's reference loaders read them.

The reference rules are rewritten here from their sources, not imported:
- VIGOR (Jeff-Zilence/VIGOR dataloader.py) and CCVPE (tudelft-iv/CCVPE datasets.py, VIGORDataset): a line's fields
  1, 4, 7, 10 are the positive and the three semi-positive satellites; fields 2-3, 5-6, 8-9, 11-12 their
  (row, col) offsets; a satellite's index is its place in satellite_list.txt;
- CCVPE: the panorama's pixel in the 640 px tile is (320 + row offset, 320 - col offset); metres per pixel per
  city from train_VIGOR.py; with semi-positives, a tile whose |offset| reaches 320 is skipped.
"""
import os
from pathlib import Path

import numpy as np
import pytest
from geoloc import registry
from geoloc.data.geo import latlon_to_offset
from geoloc.datasets.vigor import CITIES, METRES_PER_PX, ORIGINAL_METRES_PER_PX, vigor_split

FIXTURES = Path(__file__).parents[1] / "fixtures" / "released" / "vigor_corrected"
FIXTURE_CITIES = ["Chicago", "NewYork", "Seattle"]
# CCVPE train_VIGOR.py's metres per pixel, written out again so that a changed constant fails here
CCVPE_METRES_PER_PX = {"NewYork": 0.113248, "Seattle": 0.100817, "SanFrancisco": 0.118141, "Chicago": 0.111262}


def reference_lines(splits: Path, city: str, split: str) -> list[dict]:
    """One city's split file as the reference loaders read it: satellite names for the indices, offsets as floats,
    CCVPE's ground-truth pixels."""
    rows = []
    for line in (splits / city / f"same_area_balanced_{split}__corrected.txt").read_text().splitlines():
        if not line.strip():
            continue
        data = line.split(" ")
        delta = np.array([data[2:4], data[5:7], data[8:10], data[11:13]]).astype(float)
        rows.append({"panorama": data[0], "satellites": [data[i] for i in (1, 4, 7, 10)], "delta": delta,
                     "gt_px": np.stack([320 + delta[:, 0], 320 - delta[:, 1]], 1)})
    return rows


def read_through_config(root: Path, split: str, cities: list[str], **keys):
    """The reader as `dataset=vigor dataset.root=ROOT dataset.cities=[...]` builds it."""
    return registry.build("dataset", {"name": "vigor", "cities": cities, **keys}, root=str(root), split=split)


def assert_agrees(split_read, splits: Path, cities: list[str], split: str) -> int:
    """geoloc's split against the reference rules, line by line -> the number of lines compared."""
    rows = [r for city in cities for r in reference_lines(splits, city, split)]
    assert split_read.num_queries == len(rows)
    names = np.array([p.name for p in split_read.references])
    for i, row in enumerate(rows):
        assert split_read.queries[i].name == row["panorama"]
        assert names[split_read.positives[i]] == row["satellites"][0]
        assert names[split_read.semi_positives[i]].tolist() == row["satellites"][1:]
        np.testing.assert_array_equal(split_read.query_tile_px[i], row["gt_px"][0])
        np.testing.assert_array_equal(split_read.query_semi_tile_px[i], row["gt_px"][1:])
    return len(rows)


@pytest.mark.parametrize("split", ["train", "test"])
def test_fixture_lines_read_as_the_reference_loaders_read_them(split):
    s = read_through_config(FIXTURES, split, FIXTURE_CITIES, splits_dir="splits__corrected")
    assert s.tile_labels == "vigor_corrected"
    assert assert_agrees(s, FIXTURES / "splits__corrected", FIXTURE_CITIES, split) >= 25
    # the default splits_dir (null) finds the corrected folder by itself
    default = read_through_config(FIXTURES, split, FIXTURE_CITIES)
    np.testing.assert_array_equal(default.query_tile_px, s.query_tile_px)


def test_the_fixture_holds_what_the_reader_must_survive():
    lines = [r for split in ("train", "test") for c in FIXTURE_CITIES
             for r in reference_lines(FIXTURES / "splits__corrected", c, split)]
    assert len(lines) >= 50
    semi = np.concatenate([r["delta"][1:] for r in lines])
    assert (np.abs(semi) > 320).any(1).sum() >= 10 and np.abs(semi).max() >= 366  # Seattle's reach 366 px
    assert max(np.abs(r["delta"][0]).max() for r in lines) == 183  # no positive leaves its tile's central half


def test_a_semi_positive_outside_its_tile_is_kept_as_released():
    """Chicago fdbS6SU2YFJSxwxwbNI0CQ: its second semi-positive is at (-321, 103), one pixel north of the tile."""
    s = vigor_split(FIXTURES, "same_area", "test", cities=["Chicago"], splits_dir="splits__corrected")
    i = next(k for k, q in enumerate(s.queries) if q.name.startswith("fdbS6SU2YFJSxwxwbNI0CQ"))
    np.testing.assert_array_equal(s.query_semi_tile_px[i, 1], [320 - 321, 320 - 103])
    assert s.semi_inside()[i].tolist() == [True, False, True]
    assert 0 <= s.query_tile_px[:, 0].min() and s.query_tile_px.max() <= 640


def test_corrected_metres_are_the_file_names_metres():
    """The corrected positives at each city's scale agree with the GPS in the file names to the labels' rounding
    (half a pixel is 5-6 cm); at VIGOR's 0.114 m a pixel, Seattle's would be 11.6% too far out."""
    s = vigor_split(FIXTURES, "same_area", "test", cities=FIXTURE_CITIES, splits_dir="splits__corrected")
    gps = np.stack([latlon_to_offset(s.reference_latlon[p], q[None])[0]
                    for p, q in zip(s.positives, s.query_latlon)])
    labels = s.query_tile_offset_m()
    assert np.abs(labels - gps).max() < 0.35
    seattle = np.array([q.parent.parent.name == "Seattle" for q in s.queries])
    wrong_scale = labels[seattle] * ORIGINAL_METRES_PER_PX / METRES_PER_PX["Seattle"]
    assert np.abs(wrong_scale - gps[seattle]).max() > 1.0


def _write_original(root: Path, city: str, lines: list[dict], satellites: str) -> None:
    """A `splits/` folder of VIGOR's original labels for the fixture's panoramas: the same tiles, offsets made at
    0.114 m a pixel from the file names' GPS and rounded, as VIGOR made them."""
    folder = root / "splits" / city
    folder.mkdir(parents=True)
    (folder / "satellite_list.txt").write_text(satellites)
    out = []
    for row in lines:
        lat, lon = (float(v) for v in row["panorama"].split(",")[1:3])
        fields = [row["panorama"]]
        for sat in row["satellites"]:
            s_lat, s_lon = (float(v) for v in sat[len("satellite_"):-len(".png")].split("_"))
            east, north = latlon_to_offset((lat, lon), np.array([[s_lat, s_lon]]))[0]
            fields += [sat] + [f"{round(v / ORIGINAL_METRES_PER_PX):.1f}" for v in (north, east)]
        out.append(" ".join(fields))
    (folder / "same_area_balanced_test.txt").write_text("\n".join(out) + "\n")


def test_original_labels_are_converted_to_true_pixels(tmp_path):
    """VIGOR's original offsets (made at 0.114 m a pixel) read at each city's scale land where the corrected
    ones do, within the 0.3 m by which SliceMatch's labels and these GPS offsets differ; read as written they would
    not (Seattle: up to 3 m closer to the tile centre)."""
    for city in FIXTURE_CITIES:
        lines = reference_lines(FIXTURES / "splits__corrected", city, "test")
        satellites = (FIXTURES / "splits__corrected" / city / "satellite_list.txt").read_text()
        _write_original(tmp_path, city, lines, satellites)
    original = vigor_split(tmp_path, "same_area", "test", cities=FIXTURE_CITIES)
    corrected = vigor_split(FIXTURES, "same_area", "test", cities=FIXTURE_CITIES)
    assert original.tile_labels == "vigor_original" and corrected.tile_labels == "vigor_corrected"
    assert np.abs(original.query_tile_px - corrected.query_tile_px).max() < 3.0
    assert np.abs(original.query_tile_offset_m() - corrected.query_tile_offset_m()).max() < 0.35
    seattle = np.array([q.parent.parent.name == "Seattle" for q in original.queries])
    unconverted = 320 + (original.query_tile_px[seattle] - 320) * METRES_PER_PX["Seattle"] / ORIGINAL_METRES_PER_PX
    assert np.abs(unconverted - corrected.query_tile_px[seattle]).max() > 10


def test_every_city_scale_is_ccvpes():
    assert METRES_PER_PX == CCVPE_METRES_PER_PX and set(METRES_PER_PX) == set(CITIES)
    assert ORIGINAL_METRES_PER_PX == 0.114  # VIGOR evaluate_from_npy.py: "0.114 is resolution in meter"


RELEASED = os.environ.get("GEOLOC_VIGOR_LABELS")


@pytest.mark.skipif(not RELEASED, reason="GEOLOC_VIGOR_LABELS is not set: name a folder holding SliceMatch's "
                    "splits__corrected/ (tudelft-iv/SliceMatch, VIGOR_corrected_labels/) to read every released line")
@pytest.mark.parametrize("split", ["train", "test"])
def test_every_released_line_reads(split, capsys):
    root = Path(RELEASED)
    cities = [c for c in CITIES if (root / "splits__corrected" / c / f"same_area_balanced_{split}__corrected.txt")
              .is_file()]
    assert cities, f"{root}/splits__corrected holds no same_area_balanced_{split}__corrected.txt"
    s = read_through_config(root, split, cities, splits_dir="splits__corrected")
    count = assert_agrees(s, root / "splits__corrected", cities, split)
    with capsys.disabled():
        print(f"\n{split}: {count} released lines of {cities} read and agree with the reference rules")


def test_a_metre_figure_is_printed_with_its_label_set(capsys):
    from geoloc.tasks.crossview.crossview_run import print_table

    print_table({"R@1": 0.5, "fine_median_m": 2.5, "metre_labels": "vigor_original"}, "vigor/same_area/test")
    out = capsys.readouterr().out
    assert "fine_median_m" in out and "2.5" in out
    assert "fine_* metres against vigor_original: VIGOR's original labels, converted from the 0.114 m" in out
