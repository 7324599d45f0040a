"""What the particle filter says about one frame: a point, a heading, a spread, and a 95% region that stays honest
when the posterior has several modes.

The posterior is weighted samples, the filter's particles and draws from its rings (together holding
`tracked_mass` of it), plus a uniform density over the gallery's extent (the rest: the chance that no answer so far
was near the truth, particle_filter.py). Two regions are given:
- the Gaussian ellipse (`in_ellipse`): the samples' mean and covariance, Mahalanobis distance squared at most the
  chi-square quantile with 2 degrees of freedom, -2 ln(1 - level) (5.991 at 95%). One ellipse over several modes
  covers the empty space between them, and the uniform part is left out;
- the highest-posterior-density region (`contains`): the points whose posterior density is at least the threshold
  tau at which the denser points hold `level` of the posterior (Hyndman 1996, "Computing and graphing highest
  density regions": tau is the weighted (1 - level) quantile of the density at samples of the posterior). The
  density is cell_density.py's box estimate plus the uniform part; where the samples hold less than `level`,
  tau falls to the uniform density and the region is the whole gallery, which is the honest answer then.
docs/sequence.md gives the coverage of each in simulation; `contains` is the calibrated one.

The point estimate is not the mean of all samples, which falls between modes: it is the main mode, found by mean
shift with a flat kernel (Comaniciu & Meer 2002) from the densest sample: MEAN_SHIFT_STEPS times, the weighted mean
of the samples within mode_radius_m of the last one. The heading is those samples' weighted circular mean.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from geoloc.sequence.cell_density import CellDensity
from geoloc.sequence.extent import GalleryExtent

MEAN_SHIFT_STEPS = 3  # from the densest sample, whose density is noisy, to the mean of the mode around it


@dataclass
class FrameEstimate:
    """position: (2,) east, north metres of the main mode; heading_deg: its heading, clockwise from north, in
    [0, 360); mean, covariance: (2,), (2, 2) the weighted mean and covariance of all samples' positions;
    tracked_mass: the posterior probability the samples hold (the rest is uniform over `extent`);
    samples: (S, 3) east, north, heading_deg (the particles, then draws from the rings); weights: (S,) summing to
    one over the samples; region_cell_m: the cell side of the density the region is read from."""

    position: np.ndarray
    heading_deg: float
    mean: np.ndarray
    covariance: np.ndarray
    tracked_mass: float
    samples: np.ndarray
    weights: np.ndarray
    extent: GalleryExtent
    region_cell_m: float
    _cache: dict = field(default_factory=dict, repr=False, compare=False)  # the density, each level's threshold

    @classmethod
    def from_samples(cls, samples, weights, tracked_mass: float, extent: GalleryExtent, region_cell_m: float,
                     mode_radius_m: float) -> FrameEstimate:
        samples, weights = np.asarray(samples, np.float64), np.asarray(weights, np.float64)
        xy = samples[:, :2]
        mean = weights @ xy
        centred = xy - mean
        covariance = (weights[:, None] * centred).T @ centred
        estimate = cls(mean, 0.0, mean, covariance, float(tracked_mass), samples, weights, extent, region_cell_m)
        centre = xy[np.argmax(estimate._density().at_own_points())]
        for _ in range(MEAN_SHIFT_STEPS):
            near = ((xy - centre) ** 2).sum(1) <= mode_radius_m ** 2
            w = weights[near] / weights[near].sum()
            centre = w @ xy[near]
        estimate.position = centre
        heading = np.radians(samples[near, 2])
        estimate.heading_deg = float(np.degrees(np.arctan2(w @ np.sin(heading), w @ np.cos(heading))) % 360.0)
        return estimate

    def in_ellipse(self, point, level: float = 0.95) -> bool:
        """Whether (2,) point lies in the samples' Gaussian `level` ellipse (chi-square, 2 degrees of freedom)."""
        d = np.asarray(point, np.float64) - self.mean
        spread = self.covariance + 1e-9 * np.eye(2)  # a degenerate cloud (all samples on one point) stays invertible
        return bool(d @ np.linalg.solve(spread, d) <= -2 * math.log(1 - level))

    def ellipse_area_m2(self, level: float = 0.95) -> float:
        """The area of the Gaussian `level` ellipse: pi * chi-square quantile * sqrt(det covariance)."""
        return float(np.pi * -2 * math.log(1 - level) * math.sqrt(max(np.linalg.det(self.covariance), 0.0)))

    def contains(self, point, level: float = 0.95) -> bool:
        """Whether (2,) point lies in the highest-posterior-density region holding `level` of the posterior."""
        point = np.asarray(point, np.float64)[None]
        return bool(self._posterior_density(point)[0] >= self._threshold(level))

    def whole_gallery(self, level: float = 0.95) -> bool:
        """Whether the `level` region is the whole extent: the samples hold too little of the posterior."""
        return self._threshold(level) <= self._uniform_density()

    def region_area_m2(self, level: float = 0.95) -> float:
        """The area of the `level` region in square metres."""
        if self.whole_gallery(level):
            return self.extent.area_m2
        density = self._density()
        cells = density.near_cells()
        centres = (cells + 0.5) * density.cell_m
        inside = self._posterior_density(centres) >= self._threshold(level)
        return float(inside.sum() * density.cell_m ** 2)

    def _density(self) -> CellDensity:
        if "density" not in self._cache:
            self._cache["density"] = CellDensity(self.samples[:, :2], self.weights, self.region_cell_m)
        return self._cache["density"]

    def _uniform_density(self) -> float:
        return (1.0 - self.tracked_mass) / self.extent.area_m2

    def _posterior_density(self, points) -> np.ndarray:
        return (self.tracked_mass * self._density().at(points)
                + self._uniform_density() * self.extent.contains(points))

    def _threshold(self, level: float) -> float:
        if not 0 < level < 1:
            raise ValueError(f"a region's level is a probability in (0, 1), got {level}")
        if level not in self._cache:
            xy = self.samples[:, :2]
            own = (self.tracked_mass * self._density().at_own_points()
                   + self._uniform_density() * self.extent.contains(xy))
            # the samples, then one standing for the uniform part, each with its posterior mass
            density = np.append(own, self._uniform_density())
            mass = np.append(self.tracked_mass * self.weights, 1.0 - self.tracked_mass)
            order = np.argsort(-density, kind="stable")
            held = np.cumsum(mass[order])
            self._cache[level] = float(density[order][min(np.searchsorted(held, level), len(held) - 1)])
        return self._cache[level]
