"""The appearance gap: two views of one place are "taken at different times".

`AppearanceGap.strength` (0..1, default 0.5 = moderate) scales every control; each control can also be set on its
own (None = derived from strength):

- sun_shift: largest change of sun azimuth between the views, degrees (elevation changes by a quarter of it);
  it moves shadows and shading.
- color_shift: standard deviation of the per-channel log gain (white balance) and of the exposure of each view.
- season_shift: largest change of the vegetation season (0 summer green .. 0.5 autumn .. 1 bare winter brown).
- traffic_change: fraction of cars and pedestrians that differ between the views (0: the same agents).
- noise_std: Gaussian sensor noise, in 8-bit levels.
- jpeg_quality: the lowest JPEG quality a view may be saved at (each view draws from [jpeg_quality, 95]).
"""
from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from .classes import VEGETATION
from .light import Sun


@dataclass(frozen=True)
class AppearanceGap:
    strength: float = 0.5
    sun_shift: float | None = None
    color_shift: float | None = None
    season_shift: float | None = None
    traffic_change: float | None = None
    noise_std: float | None = None
    jpeg_quality: int | None = None

    def __post_init__(self):
        if not 0.0 <= self.strength <= 1.0:
            raise ValueError(f"appearance gap strength must be in [0, 1], got {self.strength}")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be in [1, 100], got {self.jpeg_quality}")

    def resolved(self) -> dict:
        s = self.strength
        d = dict(sun_shift=150.0 * s, color_shift=0.12 * s, season_shift=0.8 * s,
                 traffic_change=min(1.0, 2.0 * s), noise_std=1.0 + 5.0 * s, jpeg_quality=int(round(95 - 40 * s)))
        d.update({k: v for k, v in asdict(self).items() if v is not None and k != "strength"})
        return d


@dataclass(frozen=True)
class Conditions:
    """How one view was taken."""

    sun: Sun
    season: float
    gains: tuple  # per-channel multiplicative white balance x exposure
    noise_std: float
    jpeg_quality: int


def base_conditions(rng: np.random.Generator, gap: AppearanceGap) -> Conditions:
    g = gap.resolved()
    sun = Sun(float(rng.uniform(0, 360)), float(rng.uniform(30, 70)))
    return Conditions(sun, float(rng.uniform(0.0, 0.25)), _gains(rng, g["color_shift"]), g["noise_std"],
                      int(rng.integers(g["jpeg_quality"], 96)))


def other_time(rng: np.random.Generator, gap: AppearanceGap, ref: Conditions) -> Conditions:
    """Conditions of a second view of the same place: sun, season and colour moved by at most the gap."""
    g = gap.resolved()
    shift = g["sun_shift"]
    sun = Sun(float((ref.sun.azimuth + rng.uniform(-shift, shift)) % 360),
              float(np.clip(ref.sun.elevation + rng.uniform(-shift, shift) / 4, 18, 80)))
    season = float(np.clip(ref.season + rng.uniform(-g["season_shift"], g["season_shift"]), 0, 1))
    return Conditions(sun, season, _gains(rng, g["color_shift"]), g["noise_std"],
                      int(rng.integers(g["jpeg_quality"], 96)))


def _gains(rng, std: float) -> tuple:
    return tuple(float(v) for v in np.exp(rng.normal(0, std, 3) + rng.normal(0, std)))


_AUTUMN = np.array([[0.5, 0.6, 0.0], [0.12, 0.68, 0.0], [0.0, 0.08, 0.45]], np.float32)  # rows: out r, g, b
_WINTER = np.array([[0.6, 0.35, 0.1], [0.45, 0.4, 0.1], [0.3, 0.3, 0.2]], np.float32)


def apply_season(albedo: np.ndarray, cls: np.ndarray, season: float) -> np.ndarray:
    """Recolour vegetation in place: 0 keeps it green, 0.5 turns it autumn orange, 1 bare brown-grey."""
    if season <= 0.0:
        return albedo
    m = cls == VEGETATION
    if not m.any():
        return albedo
    v = albedo[m]
    if season <= 0.5:
        w = season / 0.5
        target = v @ _AUTUMN.T
    else:
        w = 1.0
        a = (season - 0.5) / 0.5
        target = (v @ _AUTUMN.T) * (1 - a) + (v @ _WINTER.T) * a
    albedo[m] = v * (1 - w) + target * w
    return albedo


def finish(rgb: np.ndarray, cond: Conditions, rng: np.random.Generator) -> np.ndarray:
    """Float RGB in [0, 1] -> uint8 after white balance/exposure and (luminance) sensor noise."""
    gains = np.asarray(cond.gains, np.float32) * np.float32(255.0)
    out = cv2.transform(np.ascontiguousarray(rgb, np.float32), np.diag(gains))
    if cond.noise_std > 0:
        n = noise_patch(rng, out.shape[:2]) * np.float32(cond.noise_std)
        out += cv2.merge([n, n, n])
    np.maximum(out, 0, out=out)
    return cv2.convertScaleAbs(out)  # rounds to nearest and saturates at 255


@functools.lru_cache(maxsize=1)
def _noise_field() -> np.ndarray:
    return np.random.default_rng(20231121).standard_normal((2048, 2048), np.float32)


def noise_patch(rng: np.random.Generator, shape) -> np.ndarray:
    """Unit Gaussian noise of the given shape: a window of one fixed field at a random offset (a fresh draw per
    pixel costs more than the rest of the sensor model)."""
    field = _noise_field()
    h, w = shape
    if h > field.shape[0] or w > field.shape[1]:
        return rng.standard_normal((h, w), np.float32)
    y, x = rng.integers(field.shape[0] - h + 1), rng.integers(field.shape[1] - w + 1)
    return field[y : y + h, x : x + w]
