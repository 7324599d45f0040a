"""The places a single answer has named so far, kept in closed form: one answer fixes a position but no heading, so
after the route moves on, what it says is a ring.

A hypothesis h is born at frame j from one component N(mu, s^2 I) of that frame's answer (measurement.py), with
the heading theta_j uniform (panoramas are north-aligned: an image says nothing about the way of travel). The
odometry since frame j, turned by theta_j, carries it to frame t:

    x_t = x_j + R(theta_j) D,  theta_t = theta_j + phi,

D the route's displacement since frame j in the frame of its heading then, phi the turns since, R(theta) the
clockwise turn by theta. So x_t ~ N(mu + R(theta_j) D, (s^2 + v) I), theta_j ~ U[0, 2 pi): a ring of radius |D|
around mu, v the variance the odometry's noise adds (isotropic, the straight-route approximation below).

Weighing h by a later answer component N(mu_b, sigma_b^2 I) gives the mass of the two together,

    I = (1 / 2 pi) int N(mu_b; mu + R(theta) D, (s^2 + v + sigma_b^2) I) dtheta,

computed on the arc of theta where the ring passes within 6 standard deviations of mu_b (64 points), and the
posterior of that pair, from which particle_filter.py draws particles: theta from the arc's weights, then x from the
product of the two Gaussians. So particles are spent only on places two answers agree on; a particle filter that
spreads its particles over every place one answer named keeps a few per heading, too few to be there when the
second answer comes.

Odometry noise (particle_filter.py's motion model) as the variance v per axis: half the along-track variance
distance_sigma^2 sum d^2, half the across-track variance heading_sigma^2 sum_r a_r^2 (a_r: the distance travelled
since the r-th turn, a heading error at turn r being carried that far), plus position_jitter^2 per step.
"""

from __future__ import annotations

import numpy as np

from geoloc.sequence.measurement import GaussianMixture

ARC_POINTS = 64
ARC_SIGMAS = 6.0  # the arc reaches this many standard deviations either side of the ring's nearest point


class Rings:
    """The one-answer hypotheses of a route: arrays over H hypotheses."""

    def __init__(self):
        self.mu = np.empty((0, 2))  # where the answer put the camera at birth
        self.var0 = np.empty(0)  # the answer component's variance s^2
        self.mass = np.empty(0)  # posterior probability
        self.shift = np.empty((0, 2))  # D: displacement since birth, in the birth heading's frame
        self.turned = np.empty(0)  # phi, degrees
        self.steps = np.empty(0)  # turns since birth
        self.sum_d2 = np.empty(0)  # sum of squared step lengths
        self.sum_a = np.empty(0)  # sum over turns of the distance since each
        self.sum_a2 = np.empty(0)  # sum of its squares

    def __len__(self) -> int:
        return len(self.mass)

    def add(self, mixture: GaussianMixture, mass: float) -> None:
        """New hypotheses at the mixture's components, holding `mass` between them by the mixture's weights."""
        n = len(mixture.weights)
        self._set(np.concatenate([self.mu, mixture.means]), np.concatenate([self.var0, mixture.sigmas ** 2]),
                  np.concatenate([self.mass, mass * mixture.weights]), np.concatenate([self.shift, np.zeros((n, 2))]),
                  *(np.concatenate([a, np.zeros(n)]) for a in (self.turned, self.steps, self.sum_d2, self.sum_a,
                                                               self.sum_a2)))

    def keep(self, chosen: np.ndarray) -> None:
        """Keep only the hypotheses `chosen` (a boolean mask or indices)."""
        self._set(self.mu[chosen], self.var0[chosen], self.mass[chosen], self.shift[chosen], self.turned[chosen],
                  self.steps[chosen], self.sum_d2[chosen], self.sum_a[chosen], self.sum_a2[chosen])

    def _set(self, mu, var0, mass, shift, turned, steps, sum_d2, sum_a, sum_a2) -> None:
        self.mu, self.var0, self.mass, self.shift, self.turned = mu, var0, mass, shift, turned
        self.steps, self.sum_d2, self.sum_a, self.sum_a2 = steps, sum_d2, sum_a, sum_a2

    def move(self, distance_m: float, heading_change_deg: float) -> None:
        """Carry every hypothesis through one odometry step: turn, then travel."""
        self.turned = self.turned + heading_change_deg
        rad = np.radians(self.turned)
        self.shift = self.shift + distance_m * np.stack([np.sin(rad), np.cos(rad)], 1)
        self.steps = self.steps + 1
        self.sum_d2 = self.sum_d2 + distance_m ** 2
        # each earlier turn's lever grows by this step; the new turn's lever is this step
        self.sum_a2 = self.sum_a2 + 2 * distance_m * self.sum_a + self.steps * distance_m ** 2
        self.sum_a = self.sum_a + self.steps * distance_m

    def variance(self, distance_sigma: float, heading_sigma_deg: float, position_jitter_m: float) -> np.ndarray:
        """(H,) s^2 + v: each hypothesis' position variance per axis now."""
        heading_var = np.radians(heading_sigma_deg) ** 2
        return (self.var0 + 0.5 * distance_sigma ** 2 * self.sum_d2 + 0.5 * heading_var * self.sum_a2
                + self.steps * position_jitter_m ** 2)

    def ring_points(self, index: np.ndarray, birth_heading_rad: np.ndarray) -> np.ndarray:
        """(..., 2) mu + R(theta) D for hypotheses `index` and birth headings (same shape, radians)."""
        d = self.shift[index]
        c, s = np.cos(birth_heading_rad), np.sin(birth_heading_rad)
        return self.mu[index] + np.stack([d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c], -1)

    def pair_arcs(self, variance: np.ndarray, mixture: GaussianMixture):
        """The pairs (hypothesis h, component b) whose ring passes near component b: (h (P,), b (P,), theta (P, G)
        birth headings in radians, density (P, G) N(mu_b; ring point, (var_h + sigma_b^2) I), step (P,) the arc
        spacing in radians). I of the module docstring is (density.sum(1) * step) / 2 pi."""
        sd = np.sqrt(variance[:, None] + mixture.sigmas[None] ** 2)  # (H, B)
        offset = mixture.means[None] - self.mu[:, None]  # (H, B, 2)
        radius = np.hypot(self.shift[:, 0], self.shift[:, 1])[:, None]
        gap = np.abs(np.hypot(offset[..., 0], offset[..., 1]) - radius)
        h, b = np.nonzero(gap <= ARC_SIGMAS * sd)
        sd, offset, radius = sd[h, b], offset[h, b], radius[h, 0]
        # the birth heading that turns D onto the offset: bearings clockwise from north
        centre = (np.arctan2(offset[:, 0], offset[:, 1])
                  - np.arctan2(self.shift[h, 0], self.shift[h, 1]))
        half = np.minimum(np.pi, ARC_SIGMAS * sd / np.maximum(radius, 1e-12))
        step = 2 * half / ARC_POINTS
        theta = centre[:, None] + step[:, None] * (np.arange(ARC_POINTS) + 0.5 - ARC_POINTS / 2)
        points = self.ring_points(np.repeat(h[:, None], ARC_POINTS, 1), theta)
        d2 = ((points - mixture.means[b][:, None]) ** 2).sum(-1)
        var = sd[:, None] ** 2
        return h, b, theta, np.exp(-0.5 * d2 / var) / (2 * np.pi * var), step
