"""Metres between GPS positions, and metre offsets around an origin as latitude / longitude.

Both use a sphere of the mean Earth radius (IUGG, 6,371,008.8 m). VIGOR's own code uses the spherical law of
cosines with R = 6,371,004 m; the two agree to under a millimetre at the distances of a satellite tile, and the
haversine form stays exact for distances of a few centimetres, where the arccos form loses its digits.
"""
from __future__ import annotations

import numpy as np

EARTH_RADIUS_M = 6_371_008.8


def haversine_m(a, b) -> np.ndarray:
    """Great-circle distance in metres between (..., 2) arrays of (lat, lon) degrees (broadcast against each
    other): 2 R asin(sqrt(sin^2(dlat/2) + cos(lat_a) cos(lat_b) sin^2(dlon/2)))."""
    a, b = np.radians(np.asarray(a, np.float64)), np.radians(np.asarray(b, np.float64))
    if a.shape[-1:] != (2,) or b.shape[-1:] != (2,):
        raise ValueError(f"haversine_m takes (..., 2) arrays of (lat, lon), got shapes {a.shape} and {b.shape}")
    dlat, dlon = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    h = np.sin(dlat / 2) ** 2 + np.cos(a[..., 0]) * np.cos(b[..., 0]) * np.sin(dlon / 2) ** 2
    return 2 * EARTH_RADIUS_M * np.arcsin(np.sqrt(np.clip(h, 0.0, 1.0)))


def wrapped_degrees(longitude) -> np.ndarray:
    """Longitudes (or their differences) in degrees, brought into [-180, 180] by whole turns: 179.9 + 0.2 is -179.9,
    and two places either side of the 180° meridian differ by a fraction of a degree, not by nearly 360. Values
    already in range are returned exactly as they are."""
    longitude = np.asarray(longitude, np.float64)
    return np.where(np.abs(longitude) <= 180.0, longitude, (longitude + 180.0) % 360.0 - 180.0)


def offset_to_latlon(origin, east_m, north_m) -> np.ndarray:
    """(lat, lon) degrees of points east_m / north_m metres from origin (lat, lon), on the local tangent plane:
    lat = lat0 + north / R, lon = lon0 + east / (R cos lat0), wrapped into [-180, 180]. -> (..., 2). Good to a few
    centimetres within a kilometre of the origin, which is all the synthetic cities span."""
    lat0, lon0 = (float(v) for v in origin)
    east, north = np.broadcast_arrays(np.asarray(east_m, np.float64), np.asarray(north_m, np.float64))
    lat = lat0 + np.degrees(north / EARTH_RADIUS_M)
    lon = wrapped_degrees(lon0 + np.degrees(east / (EARTH_RADIUS_M * np.cos(np.radians(lat0)))))
    return np.stack([lat, lon], -1)


def latlon_to_offset(origin, latlon) -> np.ndarray:
    """The inverse of offset_to_latlon: (..., 2) (lat, lon) degrees -> (..., 2) (east, north) metres, the
    longitude difference taken the short way round (across the 180° meridian where that is shorter)."""
    lat0, lon0 = (float(v) for v in origin)
    latlon = np.asarray(latlon, np.float64)
    north = np.radians(latlon[..., 0] - lat0) * EARTH_RADIUS_M
    east = np.radians(wrapped_degrees(latlon[..., 1] - lon0)) * EARTH_RADIUS_M * np.cos(np.radians(lat0))
    return np.stack([east, north], -1)


def centre_latlon(latlon) -> np.ndarray:
    """(2,) the mean position of (N, 2) (lat, lon) degrees, the longitudes averaged as offsets from the first (the
    short way round), so places either side of the 180° meridian have their centre among them, not at 0°."""
    latlon = np.asarray(latlon, np.float64)
    lon0 = latlon[0, 1]
    return np.array([latlon[:, 0].mean(), float(wrapped_degrees(lon0 + wrapped_degrees(latlon[:, 1] - lon0).mean()))])


def distance_m(a, b, kind: str) -> np.ndarray:
    """Metres between (..., 2) positions of one kind: "latlon" (degrees; haversine) or "xy" (metres in one
    projected frame, e.g. UTM; Euclidean)."""
    if kind == "latlon":
        return haversine_m(a, b)
    if kind == "xy":
        return np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64), axis=-1)
    raise ValueError(f"position kind must be 'latlon' or 'xy', got {kind!r}")
