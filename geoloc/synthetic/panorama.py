"""Equirectangular street panoramas, in the CVUSA / CVACT orientation.

Column j looks at compass bearing 180 + 360*j/W degrees: column 0 south, the centre column north, bearing growing
to the right (clockwise seen from above). That is the angle the SAFA polar transform of a north-up aerial tile
puts in column j, so the two line up. Rows are equirectangular with the same angular step as the columns
(360/W degrees per pixel); `horizon` gives the horizon's row as a fraction of the height:
- CVUSA crop (1232 x 224): horizon at 0.58 H, measured on the real samples (road vanishing points); the rows
  span about +38 to -27 degrees of elevation.
- CVACT full sphere (1664 x 832): horizon at 0.5 H, rows span +90 to -90 degrees.
"""
from __future__ import annotations

import numpy as np

CVUSA_HORIZON = 0.58
SPHERE_HORIZON = 0.5


def panorama_rays(height: int, width: int, horizon: float):
    """-> az_deg (W,), tan_el (H, 1) for pixel centres."""
    j = np.arange(width, dtype=np.float64)
    az = (180.0 + 360.0 * j / width) % 360.0
    deg = 360.0 / width
    el = (horizon * height - (np.arange(height) + 0.5)) * deg
    tan_el = np.tan(np.deg2rad(np.clip(el, -89.5, 89.5)))[:, None]
    return az, tan_el


def panorama_column_bearing(j, width: int):
    """Compass bearing (degrees) seen by panorama column j."""
    return (180.0 + 360.0 * np.asarray(j, np.float64) / width) % 360.0
