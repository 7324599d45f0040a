"""Where each query lies in its tiles, and the tiles' ground scale: VIGOR's offsets (released, SliceMatch's
corrected files, the synthetic tree's unrounded truth) and the one-to-one layouts' centred cameras."""
import json
from pathlib import Path

import numpy as np
import pytest
from geoloc.data.geo import latlon_to_offset
from geoloc.datasets.cvact import cvact
from geoloc.datasets.cvusa import cvusa
from geoloc.data.tile_offsets import OFFSETS_FILE
from geoloc.datasets.vigor import METRES_PER_PX, vigor_split
from geoloc.synthetic import MARKER, generate

from conftest import write_cvusa
from helpers.cvact_data import write_act_mat

# a released line (Chicago, SliceMatch's corrected test file; docs/conventions.md "VIGOR split lines"): the
# positive's centre is 23 px north and 29 px west of the panorama; its other semi-positives lie further off
# (tests/fixtures/released holds the real lines)
PANO = "L-1poX8YZAmBZVLMqBu-4w,41.877949,-87.689396,.jpg"
SATS = ["satellite_41.877971796211014_-87.68943505304125.png", "satellite_41.877971796211014_-87.68899446364951.png",
        "satellite_41.87764359775486_-87.68943505304125.png", "satellite_41.87764359775486_-87.68899446364951.png"]
LINE = f"{PANO} {SATS[0]} 23.0 -29.0 {SATS[1]} 20.0 300.0 {SATS[2]} -270.0 -29.0 {SATS[3]} -270.0 300.0\n"
# VIGOR's original labels were made at 0.114 m a pixel: in Chicago's true pixels they are this much larger
TO_CHICAGO_PX = 0.114 / 0.111262


def _release(root: Path, folder: str = "splits", suffix: str = "", line: str = LINE) -> Path:
    city = root / folder / "Chicago"
    city.mkdir(parents=True)
    (city / "satellite_list.txt").write_text("".join(s + "\n" for s in SATS))
    for name in ("same_area_balanced_train", "same_area_balanced_test", "pano_label_balanced"):
        (city / f"{name}{suffix}.txt").write_text(line)
    return root


def test_released_offsets_give_pixel_positions_and_metres(tmp_path):
    s = vigor_split(_release(tmp_path, "splits__corrected", "__corrected"), "same_area", "test", cities=["Chicago"])
    assert s.reference_size_px.tolist() == [[640, 640]] * 4 and s.tile_labels == "vigor_corrected"
    assert s.reference_metres_per_px.tolist() == [METRES_PER_PX["Chicago"]] * 4 == [0.111262] * 4
    # row = 320 + north offset, col = 320 - east offset (CCVPE's datasets.py)
    assert s.query_tile_px.tolist() == [[343.0, 349.0]]
    assert s.query_semi_tile_px.tolist() == [[[340.0, 20.0], [50.0, 349.0], [50.0, 20.0]]]
    # the panorama is 29 px east and 23 px south of the positive's centre; the file names' GPS agree to ~0.3 m
    east, north = s.query_tile_offset_m()[0]
    assert (east, north) == pytest.approx((29 * 0.111262, -23 * 0.111262))
    gps = latlon_to_offset(s.reference_latlon[s.positives[0]], s.query_latlon[0])
    np.testing.assert_allclose(gps, [east, north], atol=0.3)


def test_original_offsets_are_read_at_the_scale_they_were_made_with(tmp_path):
    """The same numbers in VIGOR's own `splits/` files mean 0.114 m a pixel: converted to the city's pixels."""
    s = vigor_split(_release(tmp_path), "same_area", "test", cities=["Chicago"])
    assert s.tile_labels == "vigor_original"
    np.testing.assert_allclose(s.query_tile_px, [[320 + 23 * TO_CHICAGO_PX, 320 + 29 * TO_CHICAGO_PX]])
    np.testing.assert_allclose(s.query_tile_offset_m(), [[29 * 0.114, -23 * 0.114]])


def test_a_positive_outside_its_tile_is_refused_a_semi_positive_is_kept(tmp_path):
    root = _release(tmp_path, "splits__corrected", "__corrected", LINE.replace("20.0 300.0", "20.0 330.0"))
    s = vigor_split(root, "same_area", "test", cities=["Chicago"])
    assert s.query_semi_tile_px[0, 0].tolist() == [340.0, -10.0] and s.semi_inside().tolist() == [[False, True, True]]
    (root / "splits__corrected/Chicago/same_area_balanced_test__corrected.txt").write_text(
        LINE.replace("23.0 -29.0", "23.0 -330.0"))
    with pytest.raises(ValueError, match=r"query_tile_px of query 0 .* is \[343.0, 650.0\], outside tile 0"):
        vigor_split(root, "same_area", "test", cities=["Chicago"])
    root = _release(tmp_path / "original")
    (root / "splits/Chicago/same_area_balanced_test.txt").write_text(LINE.replace("23.0", "nan"))
    with pytest.raises(ValueError, match=":1: the pixel offsets must be finite"):
        vigor_split(root, "same_area", "test", cities=["Chicago"])


def test_an_unknown_city_has_no_scale(tmp_path):
    _release(tmp_path)
    (tmp_path / "splits/Chicago").rename(tmp_path / "splits/Boston")
    s = vigor_split(tmp_path, "same_area", "test", cities=["Boston"])
    assert s.reference_metres_per_px is None and s.query_tile_px.tolist() == [[343.0, 349.0]]  # as written


@pytest.mark.parametrize("setting, split", [("same_area", "train"), ("same_area", "test"), ("cross_area", "test")])
def test_slicematch_corrected_files_are_read_as_released(tmp_path, setting, split):
    """splits__corrected/<City>/*__corrected.txt beside satellite_list.txt, same 13-field lines."""
    root = _release(tmp_path, "splits__corrected", "__corrected", LINE.replace("23.0 -29.0", "21.0 -30.0"))
    s = vigor_split(root, setting, split, cities=["Chicago"], splits_dir="splits__corrected")
    assert s.queries == [root / "Chicago" / "panorama" / PANO] and s.query_tile_px.tolist() == [[341.0, 350.0]]
    assert s.references[0] == root / "Chicago" / "satellite" / SATS[0]
    assert vigor_split(root, setting, split, cities=["Chicago"]).tile_labels == "vigor_corrected"  # the default
    with pytest.raises(FileNotFoundError, match="city 'Chicago'"):  # the original labels are elsewhere
        vigor_split(root, setting, split, cities=["Chicago"], splits_dir="splits")


def test_slicematch_folder_through_the_registered_reader(tmp_path):
    from geoloc import registry

    root = _release(tmp_path, "splits__corrected", "__corrected")
    section = {"name": "vigor", "cities": ["Chicago"], "splits_dir": "splits__corrected"}
    s = registry.build("dataset", section, root=str(root), split="val")
    assert s.num_queries == 1 and s.query_view == "sphere"


def test_a_folder_with_both_namings_is_refused(tmp_path):
    root = _release(tmp_path)
    (root / "splits/Chicago/same_area_balanced_test__corrected.txt").write_text(LINE)
    with pytest.raises(ValueError, match="holds both same_area_balanced_test.txt and same_area_balanced_test__"):
        vigor_split(root, "same_area", "test", cities=["Chicago"])


@pytest.fixture(scope="module")
def synthetic_vigor(tmp_path_factory):
    return generate("vigor", tmp_path_factory.mktemp("vigor") / "ds", seed=5, preset="vigor_tiny", progress=False)


def _gps_pixels(s):
    """Each query's (row, col) in its positive and semi-positive tiles from the file names' lat/lon alone."""
    tiles = np.column_stack([s.positives, s.semi_positives])
    east, north = np.moveaxis([[latlon_to_offset(s.reference_latlon[t], q) for t in row]
                               for row, q in zip(tiles, s.query_latlon)], -1, 0)
    scale, half = s.reference_metres_per_px[tiles], s.reference_size_px[tiles, 0] / 2
    return np.stack([half - north / scale, half + east / scale], -1)


def test_synthetic_positions_agree_with_the_file_names(synthetic_vigor, tmp_path):
    """vigor_tiny: 96 m tiles of 64 px. With the unrounded offsets the pixel positions are the file names' GPS to
    a thousandth of a pixel; from the split lines alone (rounded to whole pixels) within half a pixel."""
    cities = ["Chicago", "NewYork"]
    s = vigor_split(synthetic_vigor, "same_area", "train", cities=cities)
    assert s.reference_size_px.tolist() == [[64, 64]] * s.num_references
    np.testing.assert_allclose(s.reference_metres_per_px, 96.0 / 64)
    np.testing.assert_allclose(s.reference_extent_m, 96.0)
    found = np.concatenate([s.query_tile_px[:, None], s.query_semi_tile_px], 1)
    gps = _gps_pixels(s)
    assert np.abs(found - gps).max() < 1e-3
    assert np.abs(found[:, 0] - 32).max() <= 16  # positives: the central quarter
    assert np.abs(found - np.round(found)).max() > 0.05  # the truth is not whole pixels
    (synthetic_vigor / OFFSETS_FILE).rename(tmp_path / OFFSETS_FILE)
    try:
        rounded = vigor_split(synthetic_vigor, "same_area", "train", cities=cities)
    finally:
        (tmp_path / OFFSETS_FILE).rename(synthetic_vigor / OFFSETS_FILE)
    found = np.concatenate([rounded.query_tile_px[:, None], rounded.query_semi_tile_px], 1)
    assert np.abs(found - gps).max() <= 0.5 + 1e-3 and np.array_equal(found, np.round(found))


def _tree(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_a_dataset_rendered_before_the_truth_file_gets_it_untouched(synthetic_vigor, tmp_path):
    import shutil

    old = shutil.copytree(synthetic_vigor, tmp_path / "old")
    (old / OFFSETS_FILE).unlink()
    before = _tree(old)
    assert generate("vigor", old, seed=5, preset="vigor_tiny", progress=False) == old
    after = _tree(old)
    assert after.pop(OFFSETS_FILE) == _tree(synthetic_vigor)[OFFSETS_FILE] and after == before  # images, marker kept
    truth = json.loads((old / OFFSETS_FILE).read_text())
    pano = next(iter(truth["offsets"]["Chicago"]))
    truth["offsets"]["Chicago"][pano] = {k: [v[0] + 1.0, v[1]] for k, v in truth["offsets"]["Chicago"][pano].items()}
    (old / OFFSETS_FILE).write_text(json.dumps(truth))
    with pytest.raises(ValueError, match=f"offsets in {OFFSETS_FILE} .* do not round to the split line's"):
        vigor_split(old, "cross_area", "test", cities=["Chicago"])
    del truth["offsets"]["Chicago"][pano]
    (old / OFFSETS_FILE).write_text(json.dumps(truth))
    with pytest.raises(ValueError, match=f"{OFFSETS_FILE} has no offsets for panorama {pano}"):
        vigor_split(old, "cross_area", "test", cities=["Chicago"])


def test_one_to_one_cameras_sit_at_the_tile_centre(tmp_path):
    """Released CVUSA / CVACT: their tile sizes, no scale; the synthetic cvusa tree: its renderer's scale."""
    real = cvusa(str(write_cvusa(tmp_path / "cvusa", 2, 1)), "train")
    assert real.reference_size_px.tolist() == [[750, 750]] * 2 and real.reference_metres_per_px is None
    assert real.query_tile_px.tolist() == [[375.0, 375.0]] * 2
    act = tmp_path / "cvact"
    act.mkdir()
    write_act_mat(act, ["a", "b"], [1], [2])
    assert cvact(str(act), "val").query_tile_px.tolist() == [[600.0, 600.0]]
    # tiny: 96 m of 1 m cells drawn at 64 px
    root = generate("cvusa", tmp_path / "synthetic", train=2, val=1, seed=0, preset="tiny", progress=False)
    s = cvusa(str(root), "train")
    assert s.reference_size_px.tolist() == [[64, 64]] * 2 and s.query_tile_px.tolist() == [[32.0, 32.0]] * 2
    np.testing.assert_allclose(s.reference_metres_per_px, 1.5)
    np.testing.assert_array_equal(s.query_tile_offset_m(), 0.0)
    marker = json.loads((root / MARKER).read_text())
    (root / MARKER).write_text(json.dumps({**marker, "complete": False}))  # an unfinished render: refused, not read
    with pytest.raises(ValueError, match="unfinished geoloc synthetic render"):  # as a release's frame and scale
        cvusa(str(root), "train")
