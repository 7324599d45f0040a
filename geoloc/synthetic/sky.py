"""Sky colour for any viewing direction: a horizon-to-zenith gradient, a sun glow and drifting clouds."""
from __future__ import annotations

import cv2
import numpy as np

from .light import Sun


class Sky:
    """One sky per view. Clouds are a smooth noise field over (azimuth, elevation), periodic in azimuth."""

    def __init__(self, rng: np.random.Generator, sun: Sun, cover: float | None = None):
        self.sun = sun
        self.cover = float(rng.uniform(0.05, 0.6) if cover is None else cover)
        self.zenith = (np.array([0.22, 0.42, 0.78]) * rng.uniform(0.85, 1.1)).astype(np.float32)
        self.horizon = (np.array([0.72, 0.8, 0.9]) * rng.uniform(0.9, 1.05)).astype(np.float32)
        noise = np.zeros((24, 96), np.float32)
        for scale, amp in ((3, 1.0), (6, 0.5), (12, 0.25), (24, 0.12)):
            small = rng.standard_normal((max(2, scale // 2), scale * 2)).astype(np.float32)
            small = np.concatenate([small, small[:, :1]], 1)  # wrap in azimuth
            big = cv2.resize(small, (97, 24), interpolation=cv2.INTER_CUBIC)[:, :96]
            noise += amp * big
        noise = (noise - noise.mean()) / (noise.std() + 1e-6)
        wrapped = np.concatenate([noise, noise[:, :1]], 1)
        self.noise = cv2.resize(wrapped, (361, 90), interpolation=cv2.INTER_LINEAR)[:, :360]  # 1 degree cells

    def color(self, azimuth_deg: np.ndarray, tan_el: np.ndarray) -> np.ndarray:
        """azimuth (...) compass degrees, tan of elevation (...) -> (..., 3) float RGB in [0, 1]."""
        el = np.arctan(np.maximum(tan_el, 0.0).astype(np.float32))
        azimuth_deg = np.asarray(azimuth_deg, np.float32)
        t = np.sqrt(np.clip(el * np.float32(2 / np.pi), 0, 1))
        rgb = self.horizon * (1 - t)[..., None] + self.zenith * t[..., None]
        s = self.sun.vector()
        az = np.deg2rad(azimuth_deg)
        ce = np.cos(el)
        cos_sun = ce * np.sin(az) * s[0] + ce * np.cos(az) * s[1] + np.sin(el) * s[2]
        c = np.clip(cos_sun, 0, 1).astype(np.float32)
        c4 = (c * c) ** 2
        c8 = c4 * c4
        rgb = rgb + (0.35 * c8 * c8 * c8)[..., None]  # cos^24: a tight glow around the sun
        # Clouds: sample the noise field; stretch it towards the horizon like a cloud deck seen in perspective.
        iu = np.mod(azimuth_deg, 360.0).astype(np.int32) % 360
        iv = (np.clip(1.0 - np.sqrt(np.clip(el / (np.pi / 2), 0, 1)), 0, 1) * 89).astype(np.int32)
        n = self.noise[iv, iu]
        thresh = 1.4 - 2.6 * self.cover
        cloud = np.clip((n - thresh) * 1.2, 0, 1) * np.clip(el * 12, 0, 1)
        white = np.array([0.95, 0.95, 0.96], np.float32) * (0.8 + 0.2 * np.clip(n - thresh, 0, 1))[..., None]
        return np.clip(rgb * (1 - cloud[..., None]) + white * cloud[..., None], 0, 1).astype(np.float32)
