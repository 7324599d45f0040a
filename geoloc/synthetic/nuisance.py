"""Nuisances drawn apart for the two views of a place (`SynthConfig.view_nuisance`, a strength s in (0, 1]; None,
the default, draws none and leaves every pixel as before).

The appearance gap (appearance.py) already moves the sun, season, white balance, exposure, sensor noise and traffic
between the views. With view_nuisance, each view also draws on its own, from a stream of the place's seed that the
rest of the sample does not use (so resume and determinism hold):
- material gains: per class, a log-normal RGB gain of standard deviation 0.15 s per channel (roofs repainted, a
  road resurfaced, lawns of another green: ground materials, building styles and vegetation differ between the
  captures);
- sensor response: a gamma of exp(U(-0.2 s, 0.2 s));
- haze: the street view's fog distance (street.FOG_DIST_M) times exp(U(-0.7 s, 0.7 s)); the aerial view blended towards a pale haze
  colour by U(0, 0.25 s);
- the aerial tile's scale: its ground side times exp(U(-0.1 s, 0.1 s)), rounded to an even number of cells (a tile
  of another zoom or a misregistered scale);
- the street camera: its height times exp(U(-0.2 s, 0.2 s)) and its pitch U(-3 s, 3 s) degrees (the horizon's row
  moves by that angle).

Not drawn per view: road widths and the layout of the place (one world is shared by both views, so they would
need a second world), and a rotation of the tile (the polar transform assumes a north-up tile; a misregistered
rotation is left out).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .classes import ALL_CLASSES

HAZE_RGB = np.array([0.78, 0.80, 0.84], np.float32)


@dataclass(frozen=True)
class ViewNuisance:
    """One view's draws: class_gains (classes x 3), gamma, and the view's own haze, scale and camera values."""

    class_gains: np.ndarray
    gamma: float
    fog_factor: float  # street: fog distance multiplier
    haze: float  # aerial: blend towards HAZE_RGB
    tile_scale: float  # aerial: ground side multiplier
    height_factor: float  # street: camera height multiplier
    pitch_deg: float  # street: positive looks up (the horizon row moves down)


def draw(rng: np.random.Generator, strength: float) -> ViewNuisance:
    """One view's nuisances at strength s (the module docstring's distributions)."""
    s = float(strength)
    gains = np.exp(rng.normal(0.0, 0.15 * s, (len(ALL_CLASSES), 3))).astype(np.float32)
    return ViewNuisance(class_gains=gains, gamma=float(np.exp(rng.uniform(-0.2 * s, 0.2 * s))),
                        fog_factor=float(np.exp(rng.uniform(-0.7 * s, 0.7 * s))), haze=float(rng.uniform(0, 0.25 * s)),
                        tile_scale=float(np.exp(rng.uniform(-0.1 * s, 0.1 * s))),
                        height_factor=float(np.exp(rng.uniform(-0.2 * s, 0.2 * s))),
                        pitch_deg=float(rng.uniform(-3.0 * s, 3.0 * s)))


def scaled_tile_m(tile_m: float, cell_m: float, scale: float, world_cells: int) -> float:
    """The tile's ground side times `scale`, as an even number of cells that fits the world."""
    cells = min(2 * int(round(tile_m * scale / cell_m / 2)), world_cells - world_cells % 2)
    return cells * cell_m


def horizon_with_pitch(horizon: float, pitch_deg: float, height: int, width: int) -> float:
    """The horizon's row fraction once the camera pitches up by pitch_deg (rows of 360 / width degrees)."""
    return horizon + pitch_deg / (360.0 / width) / height


def respond(rgb: np.ndarray, nuisance: ViewNuisance, aerial: bool) -> np.ndarray:
    """Float RGB in [0, 1] -> the view's haze (aerial) and sensor gamma, in place where it can."""
    if aerial and nuisance.haze > 0:
        rgb = rgb * np.float32(1 - nuisance.haze) + HAZE_RGB * np.float32(nuisance.haze)
    np.clip(rgb, 0.0, 1.0, out=rgb)
    return np.power(rgb, np.float32(nuisance.gamma), out=rgb)
