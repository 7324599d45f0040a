"""VPR file names (geoloc/data/vpr_names.py) read as the field's reference reads them (gmberton/VPR-methods-
evaluation, test_dataset.py, its rule rewritten in helpers/vpr_reference.py), and UTM zones (geoloc/data/
utm_zones.py): which zones share a frame, and the errors of bad names and zones."""

from __future__ import annotations

import pytest
from geoloc.data.utm_zones import one_zone, parse_zone, same_frame
from geoloc.data.vpr_names import vpr_position

from helpers.vpr_reference import reference_east_north  # gmberton/VPR-methods-evaluation, test_dataset.py

NAMES = [
    "@500123.4@4649876.5@.jpg",  # the minimal form
    "@0584315.52@4477256.79@17@T@040.44548@-079.99551@000000@@@@@@@@.jpg",  # Pitts30k, as the downloader writes it
    "@549112.81@4179935.75@10@S@37.76812@-122.43515@@@@@@@@@@.jpg",  # the 8 fields and empty ones after them
    "@500000.00@5400000.00@32@U@@@pano7@@@@.png",  # lat and lon empty
    "@500000.00@5400000.00@@@48.75@9.18@.jpeg",  # zone and letter empty
    "@500000.00@5400000.00@32@@.jpg",  # a zone without its letter
    "@-12.5@-0.25@.jpg",  # negative and decimal
    "@-3e2@4.5E-1@@@@@.png",  # exponents
    "@ 7.0@8 @.jpg",  # white space, which float() takes
    "0001@302.5@-17@33@N@.jpg",  # a prefix before the first '@', which neither reads
]


@pytest.mark.parametrize("name", NAMES)
def test_east_and_north_agree_with_the_reference_rule(name):
    path = f"/data/pitts30k/images/test/queries/{name}"  # the reference reads the whole path, geoloc the name
    east, north, _ = vpr_position(path, path)
    assert (east, north) == reference_east_north(path)


def test_the_zone_is_read_where_given():
    zones = [vpr_position(name, name)[2] for name in NAMES]
    assert zones == [None, "17T", "10S", "32U", None, "32", None, None, None, "33N"]


@pytest.mark.parametrize("name, message", [
    ("plain.jpg", r"'plain.jpg' is not a VPR name '@UTM_east@UTM_north@.jpg' or .*the fields after north optional"),
    ("@500123.4.jpg", "is not a VPR name"),
    ("@east@4649876.5@.jpg", "is not a VPR name"),
    ("@1.0@nan@.jpg", "is not a VPR name"),
    ("@1.0@2.0@pano3@.jpg", r"the zone fields of '@1.0@2.0@pano3@.jpg': UTM zone 'PANO3' is not a zone"),
    ("@1.0@2.0@61@T@.jpg", "UTM zone '61T' is not a zone: a number from 1 to 60"),
])
def test_a_bad_name_is_refused_naming_the_file_and_the_form(name, message):
    with pytest.raises(ValueError, match=message):
        vpr_position(f"/own/tiles/{name}", f"/own/tiles/{name}")


def test_zones_share_a_frame_by_number_and_hemisphere():
    assert parse_zone(" 32t ", "w") == "32T" and parse_zone("07", "w") == "7" and parse_zone("", "w") is None
    assert same_frame("32T", "32U") and same_frame("32", "32M") and same_frame("32", "32")
    assert not same_frame("32T", "33T") and not same_frame("32M", "32N")
    assert one_zone([("32", "a"), ("32T", "b"), ("32U", "c")]) == "32T" and one_zone([]) is None
    with pytest.raises(ValueError, match=r"c: UTM zone 32M differs from 32T \(b\)"):
        one_zone([("32", "a"), ("32T", "b"), ("32M", "c")])
    with pytest.raises(ValueError, match=r"w: UTM zone '32I' is not a zone"):
        parse_zone("32I", "w")
