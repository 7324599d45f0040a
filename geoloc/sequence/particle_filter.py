"""Sequence localisation with a particle filter: a route's single-image answers and its odometry, fused frame by
frame into where the camera is.

The method is the Bayes filter over the state s = (east, north, heading) solved by sequential Monte Carlo (a
bootstrap particle filter, Gordon, Salmond & Smith 1993; Thrun, Burgard & Fox, "Probabilistic Robotics", ch. 4 and
8), as cross-view sequence localisation uses it on top of image retrieval (e.g. L2RSI, MoViX): each frame's
retrieved tiles are a measurement, the odometry between frames the motion model.

- Prior: uniform over the gallery's extent (GalleryExtent: the tile centres' box padded by half a tile) and over
  headings: panoramas are north-aligned, so an image says nothing about which way the camera travels.
- Motion (odometry row i, frame i-1 -> i): each particle turns by heading_change + N(0, heading_sigma_deg^2), then
  travels distance * (1 + N(0, distance_sigma^2)) along its heading, plus N(0, position_jitter_m^2) on each axis.
- Measurement: p(z | x) = q / A + (1 - q) M(x), M the answer's Gaussian mixture (measurement.py), A the extent's
  area, q = wrong_answer_prob. Divided by (1 - q) this is eps + M(x) with eps = q / ((1 - q) A): a frame whose
  top-k holds no tile near the truth is absorbed by the floor rather than followed.
- Resampling: systematic, when the effective sample size 1 / sum w^2 falls below resample_ess_fraction * N.

Where the particles come from. Expanding the product of the likelihoods,

    prod_t (q/A + (1-q) M_t) = (q/A)^T + sum_j (q/A)^(j-1) (1-q) M_j prod_(t>j) (q/A + (1-q) M_t),

the posterior is (a) a uniform part, the chance that no answer so far was near the truth, carried as one number;
(b) the places exactly one answer has named, each a ring once the route moves on, since one answer fixes no heading
(rings.py, carried in closed form); (c) the places two or more answers agree on: the particles. When an answer
lands on a ring, that pair's share of the posterior is drawn as new particles (rings.py gives the pair's mass and
posterior), together with the particles by one systematic resampling; a share under one particle's worth stays with
its ring. The first frame's answer thus starts the filter as rings over its tiles, with the uniform part standing
for "anywhere else". Particles spread over every place one answer named (uniform headings, a few per degree) are
too few at the truth when its second answer comes; docs/sequence.md gives the figures. Up to Monte Carlo error,
the extent's edges and the rings' isotropic odometry noise, this is the exact Bayes filter
(tests/sequence/test_particle_filter.py checks it against a brute-force posterior). The point estimate and the 95%
region are estimate.py's.

Hyperparameters (FilterConfig), defaults in brackets:
- particles [5000]: N, the particles kept after each resampling;
- tile_sigma_m [25.0]: the spread of the camera around a right tile's centre. A point uniform over a 70 m tile has
  20.2 m (70 / sqrt(12)) on each axis; 25 m because the frames' errors are not independent (consecutive frames
  often retrieve the same tile) and 20.2 m covers the truth less often than it states (docs/sequence.md);
- refined_sigma_m [5.0]: the spread around a refiner's position when it is right;
- temperature [0.05]: of the tile weights softmax(score / temperature): s^2 / (m_1 - m_0) for right-tile scores
  N(m_1, s^2) and wrong-tile scores N(m_0, s^2) (measurement.py);
- wrong_answer_prob [0.5]: q, the prior probability that no tile of a frame's top-k is near the truth (1 - the
  gallery's top-k hit rate);
- distance_sigma [0.05]: odometry's distance error, relative; heading_sigma_deg [1.0]: its heading-change error per
  frame, degrees;
- position_jitter_m [0.5]: extra position noise per frame, so that copies made by resampling spread apart;
- resample_ess_fraction [0.5]: resample when the effective sample size is below this share of N;
- region_cell_m [5.0]: the cell side of the density the 95% region and the mode are read from (cell_density.py);
- mode_radius_m [40.0]: the radius of the mean-shift window that finds the main mode, the point estimate;
- ring_samples [1000]: draws standing for the rings in each frame's estimate (they are not carried forward);
- prune_mass [1e-9]: a ring holding less of the posterior joins the uniform part; max_rings [5000]: at most this
  many rings are kept, the lightest joining the uniform part;
- fuse_every_m [0]: weigh by a frame's answer only once the odometry has gone this far since the last answer weighed
  (the first frame's always is); the frames between only move the filter. Frames a few metres apart retrieve the
  same tiles, right or wrong, so their answers are not the independent measurements the product of likelihoods
  assumes. Measured on synthetic VIGOR routes (docs/sequence.md), fusing every 30 m made a lower q honest but gave
  a larger region and no more answers within 25 m, so the default fuses every frame. 0: every frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from geoloc.sequence.estimate import FrameEstimate
from geoloc.sequence.extent import GalleryExtent
from geoloc.sequence.measurement import FrameAnswer, answer_mixture
from geoloc.sequence.odometry import Motion, Odometry
from geoloc.sequence.rings import Rings


@dataclass
class FilterConfig:
    """The filter's hyperparameters; the module docstring gives each one's meaning and why its default."""

    particles: int = 5000
    tile_sigma_m: float = 25.0
    refined_sigma_m: float = 5.0
    temperature: float = 0.05
    wrong_answer_prob: float = 0.5
    distance_sigma: float = 0.05
    heading_sigma_deg: float = 1.0
    position_jitter_m: float = 0.5
    resample_ess_fraction: float = 0.5
    region_cell_m: float = 5.0
    mode_radius_m: float = 40.0
    ring_samples: int = 1000
    prune_mass: float = 1e-9
    max_rings: int = 5000
    fuse_every_m: float = 0.0

    def __post_init__(self):
        for name in ("particles", "ring_samples", "max_rings"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if not 0 <= self.prune_mass < 1:
            raise ValueError(f"prune_mass is a probability in [0, 1), got {self.prune_mass}")
        positive = ("tile_sigma_m", "refined_sigma_m", "temperature", "region_cell_m", "mode_radius_m")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be above 0, got {getattr(self, name)}")
        for name in ("distance_sigma", "heading_sigma_deg", "position_jitter_m"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} is a standard deviation, at least 0; got {getattr(self, name)}")
        if not 0 <= self.fuse_every_m < float("inf"):
            raise ValueError(f"fuse_every_m is a distance in metres, at least 0 (0: every frame), got "
                             f"{self.fuse_every_m}")
        if not 0 < self.wrong_answer_prob < 1:
            raise ValueError(f"wrong_answer_prob is a probability strictly between 0 and 1, got "
                             f"{self.wrong_answer_prob}")
        if not 0 <= self.resample_ess_fraction <= 1:
            raise ValueError(f"resample_ess_fraction is a share of the particles in [0, 1], got "
                             f"{self.resample_ess_fraction}")


def systematic_resample(weights, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) indices into weights (summing to one) drawn by systematic resampling: one uniform offset, n evenly spaced
    pointers (Kitagawa 1996). Each index appears floor(n w) or ceil(n w) times."""
    pointers = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(np.cumsum(weights), pointers, side="right"), len(weights) - 1)


class ParticleFilter:
    """The filter of one route. step() takes the frames in order; the first call starts it from the uniform prior."""

    def __init__(self, config: FilterConfig, extent: GalleryExtent, rng: np.random.Generator):
        self.config, self.extent, self.rng = config, extent, rng
        self.particles = np.empty((0, 3))  # east, north metres; heading degrees clockwise from north
        self.weights = np.empty(0)  # sum to one over the particles
        self.particle_mass = 0.0  # the posterior probability the particles hold
        self.rings = Rings()  # the places one answer named (rings.py), with their posterior probabilities
        self.uniform_mass = 1.0  # b: the posterior probability of the uniform part
        self.frames = 0

    def step(self, motion: Motion, answer: FrameAnswer | None) -> FrameEstimate:
        """Move by `motion` (the odometry into this frame; ignored at the first frame), weigh by `answer` (None:
        move only)."""
        cfg = self.config
        if self.frames:
            self._move(motion)
            self.rings.move(motion.distance_m, motion.heading_change_deg)
        self.frames += 1
        if answer is None:
            return self._estimate()
        mixture = answer_mixture(answer, cfg.temperature, cfg.tile_sigma_m, cfg.refined_sigma_m)
        q, area = cfg.wrong_answer_prob, self.extent.area_m2
        floor = q / area  # p(z | x) away from every tile of the answer
        particles = self.particle_mass * self.weights * (floor + (1 - q) * mixture.density(self.particles[:, :2]))
        ring_var = self.rings.variance(cfg.distance_sigma, cfg.heading_sigma_deg, cfg.position_jitter_m)
        h, b, theta, density, arc_step = self.rings.pair_arcs(ring_var, mixture)
        pairs = self.rings.mass[h] * (1 - q) * mixture.weights[b] * density.sum(1) * arc_step / (2 * np.pi)
        rings_stay = self.rings.mass * floor
        uniform_stay, uniform_named = self.uniform_mass * floor, self.uniform_mass * (1 - q) / area
        total = particles.sum() + pairs.sum() + rings_stay.sum() + uniform_stay + uniform_named
        particles, pairs = particles / total, pairs / total
        self.rings.mass = rings_stay / total
        self.rings.add(mixture, uniform_named / total)
        self.uniform_mass = uniform_stay / total
        held = particles.sum() + pairs.sum()
        if held > 0 and pairs.sum() / held * cfg.particles >= 1.0:
            picks = systematic_resample(np.concatenate([particles, pairs]) / held, cfg.particles, self.rng)
            chosen = picks[picks >= len(particles)] - len(particles)
            drawn = self._draw_pairs(h[chosen], b[chosen], theta[chosen], density[chosen], arc_step[chosen],
                                     ring_var, mixture)
            self.particles = np.concatenate([self.particles[picks[picks < len(particles)]], drawn])
            self.weights = np.full(cfg.particles, 1.0 / cfg.particles)
            self.particle_mass = held
        else:  # under one particle's worth: the pairs' mass stays with their rings
            np.add.at(self.rings.mass, h, pairs)
            self.particle_mass = particles.sum()
            if self.particle_mass > 0:
                self.weights = particles / self.particle_mass
                if 1.0 / (self.weights ** 2).sum() < cfg.resample_ess_fraction * cfg.particles:
                    picks = systematic_resample(self.weights, cfg.particles, self.rng)
                    self.particles, self.weights = self.particles[picks], np.full(cfg.particles, 1.0 / cfg.particles)
        self._prune_rings()
        return self._estimate()

    def _move(self, motion: Motion) -> None:
        cfg, n = self.config, len(self.particles)
        heading = (self.particles[:, 2] + motion.heading_change_deg
                   + cfg.heading_sigma_deg * self.rng.standard_normal(n))
        distance = np.maximum(motion.distance_m * (1 + cfg.distance_sigma * self.rng.standard_normal(n)), 0.0)
        rad = np.radians(heading)
        step = np.stack([distance * np.sin(rad), distance * np.cos(rad)], 1)
        xy = self.particles[:, :2] + step + cfg.position_jitter_m * self.rng.standard_normal((n, 2))
        self.particles = np.column_stack([xy, heading % 360.0])

    def _draw_pairs(self, h, b, theta, density, arc_step, ring_var, mixture) -> np.ndarray:
        """(n, 3) particles drawn from the posterior of each (ring h, answer component b) pair: the birth heading
        from the arc's weights, the position from the product of the ring's and the component's Gaussians."""
        n = len(h)
        cdf = np.cumsum(density, 1)
        point = np.minimum((cdf < self.rng.random(n)[:, None] * cdf[:, -1:]).sum(1), cdf.shape[1] - 1)
        birth = theta[np.arange(n), point] + (self.rng.random(n) - 0.5) * arc_step
        ring_mean, ring_var = self.rings.ring_points(h, birth), ring_var[h]
        answer_var = mixture.sigmas[b] ** 2
        var = 1.0 / (1.0 / ring_var + 1.0 / answer_var)
        mean = var[:, None] * (ring_mean / ring_var[:, None] + mixture.means[b] / answer_var[:, None])
        xy = mean + np.sqrt(var)[:, None] * self.rng.standard_normal((n, 2))
        heading_sd = self.config.heading_sigma_deg * np.sqrt(self.rings.steps[h])
        heading = np.degrees(birth) + self.rings.turned[h] + heading_sd * self.rng.standard_normal(n)
        return np.column_stack([xy, heading % 360.0])

    def _prune_rings(self) -> None:
        """Rings below prune_mass, and the lightest beyond max_rings, join the uniform part."""
        cfg, mass = self.config, self.rings.mass
        keep = mass >= cfg.prune_mass
        if keep.sum() > cfg.max_rings:
            keep &= mass >= np.sort(mass)[-cfg.max_rings]
        self.uniform_mass += mass[~keep].sum()
        self.rings.keep(keep)

    def _estimate(self) -> FrameEstimate:
        """The frame's estimate from the particles and ring_samples draws standing for the rings."""
        cfg, rings = self.config, self.rings
        samples, masses = [self.particles], [self.particle_mass * self.weights]
        ring_mass = rings.mass.sum()
        if ring_mass > 0:
            n = cfg.ring_samples
            which = self.rng.choice(len(rings), n, p=rings.mass / ring_mass)
            birth = self.rng.uniform(0.0, 2 * np.pi, n)
            sd = np.sqrt(rings.variance(cfg.distance_sigma, cfg.heading_sigma_deg, cfg.position_jitter_m)[which])
            xy = rings.ring_points(which, birth) + sd[:, None] * self.rng.standard_normal((n, 2))
            samples.append(np.column_stack([xy, (np.degrees(birth) + rings.turned[which]) % 360.0]))
            masses.append(np.full(n, ring_mass / n))
        mass = np.concatenate(masses)
        return FrameEstimate.from_samples(np.concatenate(samples), mass / mass.sum(), 1.0 - self.uniform_mass,
                                            self.extent, cfg.region_cell_m, cfg.mode_radius_m)


def localize_route(answers: Sequence[FrameAnswer], odometry: Odometry, extent: GalleryExtent,
                   config: FilterConfig = FilterConfig(), seed: int = 0) -> list[FrameEstimate]:
    """Each frame's estimate for a route of F frames: answers[i] is frame i's, odometry row i the motion into it.
    An answer is weighed by when config.fuse_every_m allows (fused_frames). The same seed gives the same
    estimates."""
    if len(answers) != len(odometry):
        raise ValueError(f"{len(answers)} frame answers but {len(odometry)} odometry rows: the route needs one of "
                         "each per frame")
    route = ParticleFilter(config, extent, np.random.default_rng(seed))
    fused = set(fused_frames(odometry, config.fuse_every_m))
    return [route.step(odometry.motion(i), answer if i in fused else None) for i, answer in enumerate(answers)]


def fused_frames(odometry: Odometry, fuse_every_m: float) -> list[int]:
    """The frames whose answers the filter weighs by: frame 0, then each frame at which the odometry has gone at
    least fuse_every_m metres since the last one (every frame when fuse_every_m is 0)."""
    chosen, travelled = [0], 0.0
    for i in range(1, len(odometry)):
        travelled += odometry.motion(i).distance_m
        if travelled >= fuse_every_m:
            chosen.append(i)
            travelled = 0.0
    return chosen
