"""Terrain styles and material palettes.

A style is a bag of numbers the place builders read; the palettes are base albedos (RGB uint8) that every place
jitters, so two places of the same style share a look without being copies.
"""
from __future__ import annotations

import numpy as np

STYLES = ("urban", "suburban", "rural")

# Default mix when a dataset does not ask for one style: rural first, as in CVUSA, where many places look alike.
DEFAULT_MIX = {"urban": 0.25, "suburban": 0.3, "rural": 0.45}

ASPHALT = [(72, 72, 76), (88, 86, 84), (60, 62, 66), (98, 96, 92)]
CONCRETE = [(168, 164, 156), (150, 148, 142), (182, 176, 166)]
MARKING_WHITE = (222, 222, 214)
MARKING_YELLOW = (214, 178, 60)
GRASS = [(86, 122, 54), (104, 134, 62), (74, 108, 50), (118, 140, 76)]
CROPS = [(96, 136, 52), (150, 160, 74), (182, 170, 96), (120, 150, 60), (198, 184, 120)]
SOIL = [(132, 108, 82), (118, 96, 74), (150, 128, 100), (104, 88, 70)]
TREE = [(48, 84, 40), (60, 96, 44), (40, 72, 38), (72, 100, 50)]
ROOF = [(110, 62, 52), (84, 84, 90), (132, 120, 110), (60, 60, 64), (150, 90, 70), (170, 168, 160)]
FLAT_ROOF = [(120, 120, 118), (96, 96, 98), (140, 136, 130), (80, 82, 86)]
FACADE = [(184, 168, 144), (150, 140, 128), (200, 196, 186), (132, 96, 80), (170, 150, 120), (110, 116, 124)]
HOUSE_WALL = [(220, 214, 198), (196, 180, 150), (170, 186, 196), (210, 200, 170), (160, 120, 96)]
FENCE = [(130, 110, 90), (150, 150, 150), (110, 90, 70)]
METAL = [(96, 96, 100), (130, 130, 134), (70, 74, 78)]
CAR = [(200, 200, 204), (30, 30, 34), (150, 20, 24), (40, 60, 130), (120, 124, 128), (230, 230, 230), (60, 90, 60)]
CLOTHES = [(40, 40, 60), (150, 40, 40), (200, 190, 170), (60, 80, 120), (30, 30, 30), (90, 120, 80)]


def pick(rng: np.random.Generator, palette, jitter: float = 10.0) -> tuple:
    """A palette colour with a small random offset, uniform with std `jitter` per channel (uint8 tuple).
    Called thousands of times per place, so it stays in plain Python after one draw."""
    u = rng.random(4).tolist()
    base = palette[int(u[0] * len(palette))]
    amp = 3.4641 * jitter  # uniform on [-a/2, a/2] has std a / sqrt(12)
    return tuple(min(255, max(0, int(b + (v - 0.5) * amp))) for b, v in zip(base, u[1:]))


def choose_style(rng: np.random.Generator, mix: dict | None) -> str:
    mix = mix or DEFAULT_MIX
    names = sorted(mix)
    p = np.array([mix[k] for k in names], np.float64)
    return names[int(rng.choice(len(names), p=p / p.sum()))]
