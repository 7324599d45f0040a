"""Split files as editors and copies leave them: a byte-order mark is not part of the first name, and a name listed
twice is refused with its file and both lines, in every reader of text split files (VIGOR, CVUSA, positions.csv,
the dynamic layout). A repeated VIGOR line would count its query twice: 10 queries instead of 6, and the hit rate
moves from 16.67 to 10.00."""

import codecs
import json

import numpy as np
import pytest
from test_vigor import EXAMPLE_LINE, EXAMPLE_PANO, EXAMPLE_SATS

from geoloc.data.list_files import list_lines
from geoloc.data.positions import read_positions
from geoloc.datasets.cvusa import cvusa_pairs
from geoloc.datasets.vigor import vigor_split
from geoloc.tasks.mmdip.datasets import DynamicDataset

CVUSA_ROW = "bingmap/19/{n:07d}.jpg,streetview/panos/{n:07d}.jpg,streetview/annotations/{n:07d}.png\n"


def _chicago(root, split_text: str, list_text: str | None = None):
    folder = root / "splits" / "Chicago"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "satellite_list.txt").write_bytes((list_text or "\n".join(EXAMPLE_SATS) + "\n").encode())
    (folder / "same_area_balanced_test.txt").write_bytes(split_text.encode("utf-8"))
    return folder


@pytest.mark.parametrize("mark", [codecs.BOM_UTF8, codecs.BOM_UTF16_LE])
def test_a_byte_order_mark_is_not_part_of_the_first_vigor_names(tmp_path, mark):
    folder = _chicago(tmp_path, "")
    encoding = "utf-16-le" if mark == codecs.BOM_UTF16_LE else "utf-8"
    (folder / "same_area_balanced_test.txt").write_bytes(mark + (EXAMPLE_LINE + "\r\n").encode(encoding))
    (folder / "satellite_list.txt").write_bytes(mark + "\n".join(EXAMPLE_SATS).encode(encoding))
    split = vigor_split(tmp_path, "same_area", "test", cities=["Chicago"])
    assert split.queries == [tmp_path / "Chicago" / "panorama" / EXAMPLE_PANO]  # no \ufeff before the name
    assert split.references[0] == tmp_path / "Chicago" / "satellite" / EXAMPLE_SATS[0]
    assert split.positives.tolist() == [0] and split.semi_positives.tolist() == [[1, 2, 3]]


def test_a_repeated_vigor_line_is_refused_with_both_line_numbers(tmp_path):
    other = EXAMPLE_LINE.replace(EXAMPLE_PANO, "other,41.877950,-87.689390,.jpg")
    _chicago(tmp_path, f"{EXAMPLE_LINE}\n{other}\n\n{EXAMPLE_LINE}\n")
    path = tmp_path / "splits" / "Chicago" / "same_area_balanced_test.txt"
    with pytest.raises(ValueError, match=rf"{path}:4: panorama {EXAMPLE_PANO} is listed again \(first on line 1\)"
                                         rf".*keep one of lines 1 and 4"):
        vigor_split(tmp_path, "same_area", "test", cities=["Chicago"])
    # the same panorama with other labels is the same query counted twice
    _chicago(tmp_path, f"{EXAMPLE_LINE}\n{EXAMPLE_LINE.replace('23.0', '24.0')}\n")
    with pytest.raises(ValueError, match=r"same_area_balanced_test.txt:2: panorama .* \(first on line 1\)"):
        vigor_split(tmp_path, "same_area", "test", cities=["Chicago"])


def test_cvusa_refuses_a_repeated_row_and_reads_a_utf16_file(tmp_path):
    (tmp_path / "splits").mkdir()
    csv = tmp_path / "splits" / "val-19zl.csv"
    csv.write_text(CVUSA_ROW.format(n=1) + CVUSA_ROW.format(n=2) + CVUSA_ROW.format(n=1))
    with pytest.raises(ValueError, match=rf"{csv}:3: panorama streetview/panos/0000001.jpg is listed again "
                                         r"\(first on line 1\)"):
        cvusa_pairs(tmp_path, "val")
    csv.write_text(CVUSA_ROW.format(n=1) + "bingmap/19/0000001.jpg,streetview/panos/0000002.jpg\n")
    with pytest.raises(ValueError, match=r":2: aerial image bingmap/19/0000001.jpg is listed again"):
        cvusa_pairs(tmp_path, "val")
    csv.write_bytes(codecs.BOM_UTF16_LE + CVUSA_ROW.format(n=1).encode("utf-16-le"))
    assert cvusa_pairs(tmp_path, "val") == [(tmp_path / "streetview/panos/0000001.jpg",
                                             tmp_path / "bingmap/19/0000001.jpg")]


def test_positions_file_with_a_mark_reads_and_a_repeat_is_refused(tmp_path):
    path = tmp_path / "positions.csv"
    path.write_bytes(codecs.BOM_UTF8 + b"panorama,x_m,y_m\nstreetview/panos/1.jpg,1.0,2.0\n")
    kind, xy = read_positions(tmp_path, [tmp_path / "streetview/panos/1.jpg"])
    assert kind == "xy" and xy.tolist() == [[1.0, 2.0]]
    path.write_text("panorama,x_m,y_m\nstreetview/panos/1.jpg,1.0,2.0\nstreetview/panos/1.jpg,5.0,2.0\n")
    with pytest.raises(ValueError, match=r"positions.csv:3: panorama streetview/panos/1.jpg is listed again"):
        read_positions(tmp_path, [tmp_path / "streetview/panos/1.jpg"])


def _dynamic_csv(root, text: bytes):
    (root / "splits").mkdir(parents=True, exist_ok=True)
    (root / "geoloc_synthetic.json").write_text(json.dumps({"layout": "dynamic"}))
    (root / "splits" / "val.csv").write_bytes(text)


def test_dynamic_split_csv_with_a_mark_reads_and_a_repeat_is_refused(tmp_path):
    header = b"sample,place,role,x,y,yaw,sun_azimuth,sun_elevation\n"
    _dynamic_csv(tmp_path, codecs.BOM_UTF8 + header + b"0000000,3,reference,0,0,0,0,45\n0000001,3,query,0,0,0,0,45\n")
    data = DynamicDataset(tmp_path, "val", check="off")
    assert data.samples == ["0000000", "0000001"] and data.places.tolist() == [3, 3]
    assert data.is_query.tolist() == [False, True]
    _dynamic_csv(tmp_path, header + b"0000000,3,reference,0,0,0,0,45\n0000000,3,query,0,0,0,0,45\n")
    with pytest.raises(ValueError, match=r"val.csv:3: sample 0000000 is listed again \(first on line 2\)"):
        DynamicDataset(tmp_path, "val", check="off")
    _dynamic_csv(tmp_path, b"name,place\n0000000,3\n")
    with pytest.raises(ValueError, match=r"val.csv: the first line must name the columns .* missing "
                                         r"\['sample', 'role'\]"):
        DynamicDataset(tmp_path, "val", check="off")


def test_a_list_that_is_not_text_is_named(tmp_path):
    path = tmp_path / "satellite_list.txt"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff")
    with pytest.raises(ValueError, match=rf"VIGOR satellite list {path} is not UTF-8 text"):
        list_lines(path, "VIGOR satellite list")
    assert np.all([text == text.strip() for _, text in list_lines(__file__, "this test")])
