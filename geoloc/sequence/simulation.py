"""Synthetic routes over a synthetic gallery, with single-image answers that are right only some of the time: the
ground truth the sequence filter is measured on (tests/sequence/, benchmarks/bench_sequence.py, docs/sequence.md).

- Gallery: tile centres on a square lattice of `spacing_m` (35 m) over `side_m` x `side_m` (2 km), tiles
  `tile_width_m` (70 m) wide, so that neighbouring tiles overlap by half, as VIGOR's do: every point lies in four
  tiles.
- Route: `frames` positions `step_m` (10 m) apart, starting uniformly in the gallery's central half, first heading
  uniform, each later heading turned by N(0, turn_sigma_deg^2) (a random walk that bends like a street route).
- Odometry: each step's distance times (1 + N(0, distance_noise^2)), its turn plus N(0, heading_noise_deg^2).
- Answer: with probability `hit_prob` the top-k holds one right tile (one of the four holding the camera, picked
  uniformly: a positive or a semi-positive) in a random slot, the other k - 1 tiles random; otherwise all k are
  random tiles. Scores: N(right_score, score_sigma^2) for the right tile, N(wrong_score, score_sigma^2) for the
  others, sorted best first. The matching filter temperature is score_sigma^2 / (right_score - wrong_score).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geoloc.sequence.extent import GalleryExtent
from geoloc.sequence.measurement import FrameAnswer
from geoloc.sequence.odometry import Odometry


@dataclass(frozen=True)
class SimulationConfig:
    side_m: float = 2000.0
    spacing_m: float = 35.0
    tile_width_m: float = 70.0
    frames: int = 20
    step_m: float = 10.0
    turn_sigma_deg: float = 30.0
    distance_noise: float = 0.05
    heading_noise_deg: float = 1.0
    hit_prob: float = 0.3
    top_k: int = 5
    right_score: float = 0.55
    wrong_score: float = 0.50
    score_sigma: float = 0.05

    @property
    def matched_temperature(self) -> float:
        return self.score_sigma ** 2 / (self.right_score - self.wrong_score)


@dataclass(frozen=True)
class SimulatedRoute:
    """truth: (F, 2) the camera's positions; headings_deg: (F,); answers: F FrameAnswers; odometry: what the
    filter is told; answer_right: (F,) whether the top-k holds a right tile."""

    truth: np.ndarray
    headings_deg: np.ndarray
    answers: list[FrameAnswer]
    odometry: Odometry
    answer_right: np.ndarray


class SimulatedGallery:
    """The lattice of tile centres, and routes with their answers drawn over it."""

    def __init__(self, config: SimulationConfig):
        self.config = config
        axis = np.arange(0.0, config.side_m + 1e-9, config.spacing_m)
        self.axis = axis
        east, north = np.meshgrid(axis, axis, indexing="ij")
        self.centres = np.stack([east.ravel(), north.ravel()], 1)  # row i * len(axis) + j: (axis[i], axis[j])
        self.extent = GalleryExtent.from_centres(self.centres, config.tile_width_m)

    def tiles_holding(self, point) -> np.ndarray:
        """Rows of the tiles whose square holds `point` (four inside the lattice)."""
        half = self.config.tile_width_m / 2
        near = [np.nonzero(np.abs(self.axis - v) < half)[0] for v in point]
        return (near[0][:, None] * len(self.axis) + near[1][None, :]).ravel()

    def route(self, rng: np.random.Generator) -> SimulatedRoute:
        cfg = self.config
        turn = np.concatenate([[0.0], rng.normal(0.0, cfg.turn_sigma_deg, cfg.frames - 1)])
        headings = (rng.uniform(0.0, 360.0) + np.cumsum(turn)) % 360.0
        rad = np.radians(headings)
        steps = cfg.step_m * np.stack([np.sin(rad), np.cos(rad)], 1)
        steps[0] = 0.0
        truth = rng.uniform(cfg.side_m / 4, 3 * cfg.side_m / 4, 2) + np.cumsum(steps, 0)
        distance = cfg.step_m * (1 + cfg.distance_noise * rng.standard_normal(cfg.frames))
        measured_turn = turn + cfg.heading_noise_deg * rng.standard_normal(cfg.frames)
        distance[0] = measured_turn[0] = 0.0
        right = rng.random(cfg.frames) < cfg.hit_prob
        answers = [self.answer(p, bool(r), rng) for p, r in zip(truth, right)]
        return SimulatedRoute(truth, headings, answers, Odometry(np.maximum(distance, 0.0), measured_turn), right)

    def answer(self, position, right: bool, rng: np.random.Generator) -> FrameAnswer:
        """One frame's top-k for a camera at `position`: a right tile among them when `right`."""
        cfg = self.config
        rows = rng.choice(len(self.centres), cfg.top_k, replace=False)
        scores = rng.normal(cfg.wrong_score, cfg.score_sigma, cfg.top_k)
        if right:
            slot = rng.integers(cfg.top_k)
            rows[slot] = rng.choice(self.tiles_holding(position))
            scores[slot] = rng.normal(cfg.right_score, cfg.score_sigma)
        order = np.argsort(-scores)
        return FrameAnswer(self.centres[rows[order]], scores[order])
