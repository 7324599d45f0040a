"""relight_city: one city of a synthetic VIGOR world rendered again under another sun, the same places; the source
untouched and the result readable by the VIGOR reader."""
import json
import sys

import cv2
import numpy as np
import pytest
from geoloc.datasets.vigor import vigor_split
from geoloc.synthetic import MARKER, generate
from geoloc.synthetic.relight import relight_city

from conftest import REPO


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    return generate("vigor", tmp_path_factory.mktemp("vigor") / "ds", seed=3, preset="vigor_tiny", progress=False)


def _pixels(folder):
    return {f.name: cv2.imread(str(f)) for f in sorted(folder.iterdir())}


def _state(root):
    return sorted((str(p.relative_to(root)), p.stat().st_mtime_ns, p.stat().st_size) for p in root.rglob("*"))


def test_unchanged_conditions_give_the_same_images(source, tmp_path):
    out = relight_city(source, tmp_path / "same", "Chicago")
    for sub in ("satellite", "panorama"):
        mine, theirs = _pixels(out / "Chicago" / sub), _pixels(source / "Chicago" / sub)
        assert mine.keys() == theirs.keys() and len(mine) > 0
        assert all(np.array_equal(mine[k], theirs[k]) for k in mine)


def test_a_higher_sun_changes_the_city_and_nothing_else(source, tmp_path):
    before = _state(source)
    out = relight_city(source, tmp_path / "high", "Chicago", sun_elevation=75.0)
    assert _state(source) == before  # the source is only read
    tiles, old_tiles = _pixels(out / "Chicago" / "satellite"), _pixels(source / "Chicago" / "satellite")
    assert tiles.keys() == old_tiles.keys()
    assert np.mean([np.abs(tiles[k].astype(int) - old_tiles[k]).mean() for k in tiles]) > 1.0
    panoramas = _pixels(out / "Chicago" / "panorama")
    assert panoramas.keys() == _pixels(source / "Chicago" / "panorama").keys()  # the same panoramas, re-rendered
    assert not (out / "Chicago" / "panorama").is_symlink()
    assert (out / "NewYork").resolve() == (source / "NewYork").resolve()  # other cities are linked
    marker = json.loads((out / MARKER).read_text())
    assert marker["relit"]["sun_elevation"] == 75.0 and marker["relit"]["city"] == "Chicago"
    assert marker["relit"]["was"]["sun_elevation"] != 75.0
    old = vigor_split(source, "cross_area", "train", cities=["Chicago"])
    new = vigor_split(out, "cross_area", "train", cities=["Chicago"])
    assert new.num_queries == old.num_queries > 0
    assert [q.name for q in new.queries] == [q.name for q in old.queries]
    assert np.array_equal(new.positives, old.positives) and np.allclose(new.query_tile_px, old.query_tile_px)
    assert new.reference_metres_per_px is not None  # the tile geometry, from the copied marker


def test_tiles_only_keeps_the_panoramas(source, tmp_path):
    out = relight_city(source, tmp_path / "tiles", "Chicago", sun_elevation=75.0, season=0.9, panoramas=False)
    assert (out / "Chicago" / "panorama").resolve() == (source / "Chicago" / "panorama").resolve()
    assert json.loads((out / MARKER).read_text())["relit"]["season"] == 0.9


def test_bad_requests_are_refused(source, tmp_path):
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "mine.txt").write_text("a user's file")
    with pytest.raises(FileExistsError, match="not empty"):
        relight_city(source, busy, "Chicago", sun_elevation=60.0)
    assert (busy / "mine.txt").read_text() == "a user's file"
    with pytest.raises(ValueError, match="Seattle"):
        relight_city(source, tmp_path / "a", "Seattle")  # vigor_tiny renders Chicago and New York only
    with pytest.raises(ValueError, match="sun_elevation"):
        relight_city(source, tmp_path / "b", "Chicago", sun_elevation=-5.0)
    with pytest.raises(FileNotFoundError, match=MARKER):
        relight_city(tmp_path / "busy", tmp_path / "c", "Chicago")
    (busy / MARKER).write_text("{ cut short")
    with pytest.raises(ValueError, match="not valid JSON"):
        relight_city(busy, tmp_path / "c", "Chicago")
    relit = relight_city(source, tmp_path / "d", "Chicago", sun_elevation=50.0, panoramas=False)
    with pytest.raises(ValueError, match="itself relit"):
        relight_city(relit, tmp_path / "e", "Chicago")


@pytest.mark.parametrize("flag, value", [("--sun-azimuth", "nan"), ("--sun-azimuth", "inf"), ("--sun-azimuth", "-90"),
                                         ("--sun-azimuth", "361"), ("--sun-elevation", "nan"),
                                         ("--sun-elevation", "inf"), ("--season", "nan"), ("--season", "-inf")])
def test_a_condition_that_is_not_a_finite_number_in_its_range_is_refused_before_anything(flag, value, tmp_path,
                                                                                        monkeypatch):
    """--sun-azimuth nan exited 0 with every tile black and NaN in the marker; the tool refuses it at the door,
    before the source is read (it does not exist here) or anything is written."""
    sys.path.insert(0, str(REPO / "tools"))
    import relight_vigor

    out = tmp_path / "out"
    monkeypatch.setattr(sys, "argv", ["relight_vigor.py", str(tmp_path / "nowhere"), str(out), "--city", "Chicago",
                                      f"{flag}={value}"])
    name = flag.lstrip("-").replace("-", "_")
    with pytest.raises(ValueError, match=rf"{name} must be a number in .*, got {float(value)}; nothing was written"):
        relight_vigor.main()
    assert not out.exists()
