"""Reading odometry.csv (geoloc/sequence/odometry.py): a round trip, and each fault refused with the file, the line,
what is wrong and what to write."""

from __future__ import annotations

import numpy as np
import pytest

from geoloc.sequence.odometry import Motion, odometry_text, read_odometry


def write(tmp_path, text: str):
    path = tmp_path / "odometry.csv"
    path.write_text(text, encoding="utf-8")
    return path


def test_round_trip(tmp_path):
    distance, turn = np.array([0.0, 9.85, 10.2, 0.0]), np.array([0.0, -12.5, 3.25, 180.0])
    odometry = read_odometry(write(tmp_path, odometry_text(distance, turn)))
    np.testing.assert_allclose(odometry.distance_m, distance)
    np.testing.assert_allclose(odometry.heading_change_deg, turn)
    assert len(odometry) == 4 and odometry.motion(2) == Motion(10.2, 3.25)


def test_columns_in_another_order_and_extra_columns_are_read(tmp_path):
    text = "\ufeffheading_change_deg,frame,note,distance_m\n0,0,start,0\n-5,1,turn,10\n"
    odometry = read_odometry(write(tmp_path, text))
    assert odometry.motion(1) == Motion(10.0, -5.0)


@pytest.mark.parametrize("text, message", [
    ("frame,distance_m\n0,0\n", r"odometry.csv:1: the header has no column heading_change_deg .*the first line must "
                                r"name frame,distance_m,heading_change_deg"),
    ("frame,distance,heading_change_deg\n0,0,0\n", r":1: the header has no column distance_m"),
    ("frame,distance_m,heading_change_deg\n0,0,0\n1,ten,0\n", r":3: distance_m is 'ten', not a number"),
    ("frame,distance_m,heading_change_deg\n0,0,0\n1,10,nan\n", r":3: heading_change_deg is 'nan': it must be a finite"),
    ("frame,distance_m,heading_change_deg\n0,0,0\n1,-3,0\n", r":3: distance_m is -3.0, below 0: a distance travelled "
                                                             r"is never negative"),
    ("frame,distance_m,heading_change_deg\n0,0,0\n2,10,0\n", r":3: frame 2 where frame 1 was expected: the rows must "
                                                             r"be frames 0, 1, 2, ... in order"),
    ("frame,distance_m,heading_change_deg\n0,0,0\n1,10,0\n1,10,0\n", r":4: frame 1 where frame 2 was expected"),
    ("frame,distance_m,heading_change_deg\n1,10,0\n", r":2: frame 1 where frame 0 was expected"),
    ("frame,distance_m,heading_change_deg\n0,0,0\n1.5,10,0\n", r":3: frame is '1.5': frames are whole numbers"),
    ("frame,distance_m,heading_change_deg\n0,10,5\n1,10,0\n", r":2: frame 0 moves \(10 m, 5 degrees\), but nothing "
                                                             r"comes before it: .*row 0 is 0,0,0"),
    ("frame,distance_m,heading_change_deg\n0,0,0\n1,10\n", r":3: 2 fields where the header names 3"),
    ("frame,distance_m,heading_change_deg\n", r"has a header but no frames"),
    ("", r"is empty: write the header frame,distance_m,heading_change_deg"),
])
def test_faults_are_refused_with_where_and_what_to_do(tmp_path, text, message):
    with pytest.raises(ValueError, match=message):
        read_odometry(write(tmp_path, text))
