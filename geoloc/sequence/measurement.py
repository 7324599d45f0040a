"""One frame's single-image answer, and what it says about where the camera is: a mixture of isotropic Gaussians.

The answer is the top-k tiles of a saved gallery for the frame's panorama: each tile's centre (east, north metres),
its retrieval score (cosine similarity, higher is better) and, where a fine-grained refiner ran, a position inside
the tile with the refiner's confidence that it is right. It becomes

    M(x) = sum_k w_k [c_k N(x; r_k, refined_sigma^2 I) + (1 - c_k) N(x; t_k, tile_sigma^2 I)],
    w_k = softmax(score_k / temperature),

t_k the tile centre, r_k the refined position, c_k its confidence (0 where there is none). The softmax is the
probability that tile k is the one holding the camera when scores of right and wrong tiles are Gaussian with one
spread s and means m_1 > m_0: then P(k | scores) is proportional to exp(score_k (m_1 - m_0) / s^2), a softmax
with temperature s^2 / (m_1 - m_0). M integrates to one; the filter adds the chance that no tile is right
(particle_filter.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FrameAnswer:
    """centres: (k, 2) tile centres (east, north metres), best first or in any order; scores: (k,) retrieval scores
    (-inf for an empty slot of a short list); refined: (k, 2) positions inside the tiles from a refiner, or None;
    refined_confidence: (k,) the probability each refined position is right, in [0, 1] (a refiner's calibrated
    confidence, or 1 / 0 for a kept / dropped one); None with refined given means 1 for every tile."""

    centres: np.ndarray
    scores: np.ndarray
    refined: np.ndarray | None = None
    refined_confidence: np.ndarray | None = None

    def __post_init__(self):
        centres = np.asarray(self.centres, np.float64)
        scores = np.asarray(self.scores, np.float64)
        k = len(scores)
        if centres.shape != (k, 2) or scores.ndim != 1 or k == 0:
            raise ValueError(f"a frame answer needs centres k x 2 and scores (k,), k >= 1; got shapes "
                             f"{centres.shape} and {scores.shape}")
        if not np.isfinite(centres).all() or np.isnan(scores).any() or not np.isfinite(scores.max()):
            raise ValueError("a frame answer's centres must be finite and its scores finite or -inf (an empty "
                             "slot), with at least one finite score")
        object.__setattr__(self, "centres", centres)
        object.__setattr__(self, "scores", scores)
        if self.refined is None:
            if self.refined_confidence is not None:
                raise ValueError("refined_confidence was given without refined positions")
            return
        refined = np.asarray(self.refined, np.float64)
        confidence = (np.ones(k) if self.refined_confidence is None
                      else np.asarray(self.refined_confidence, np.float64))
        if refined.shape != (k, 2) or confidence.shape != (k,):
            raise ValueError(f"refined must be k x 2 and refined_confidence (k,) for k = {k} tiles; got shapes "
                             f"{refined.shape} and {confidence.shape}")
        if not ((confidence >= 0) & (confidence <= 1)).all():
            raise ValueError(f"refined_confidence must be probabilities in [0, 1], got {confidence}")
        if not np.isfinite(refined[confidence > 0]).all():
            raise ValueError("a refined position with a confidence above 0 must be finite")
        object.__setattr__(self, "refined", refined)
        object.__setattr__(self, "refined_confidence", confidence)

    def __len__(self) -> int:
        return len(self.scores)


@dataclass(frozen=True)
class GaussianMixture:
    """sum_j weights_j N(x; means_j, sigmas_j^2 I) in the plane: means (m, 2), sigmas (m,), weights (m,) summing
    to one."""

    means: np.ndarray
    sigmas: np.ndarray
    weights: np.ndarray

    def density(self, points) -> np.ndarray:
        """(N,) the mixture's density (per square metre) at (N, 2) points."""
        points = np.asarray(points, np.float64)
        d2 = ((points[:, None, :] - self.means[None]) ** 2).sum(-1)
        var = self.sigmas ** 2
        return (np.exp(-0.5 * d2 / var) * (self.weights / (2 * np.pi * var))).sum(1)

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 2) points drawn from the mixture."""
        component = rng.choice(len(self.weights), size=n, p=self.weights)
        return self.means[component] + rng.standard_normal((n, 2)) * self.sigmas[component, None]


def tile_weights(scores, temperature: float) -> np.ndarray:
    """(k,) softmax(scores / temperature): the probability that each tile is the right one, given that one is."""
    z = np.asarray(scores, np.float64) / temperature
    e = np.exp(z - z.max())
    return e / e.sum()


def answer_mixture(answer: FrameAnswer, temperature: float, tile_sigma_m: float,
                   refined_sigma_m: float) -> GaussianMixture:
    """M(x) of the module docstring for one frame: a component per tile centre and one per refined position with a
    confidence above 0."""
    w = tile_weights(answer.scores, temperature)
    if answer.refined is None:
        return GaussianMixture(answer.centres, np.full(len(w), float(tile_sigma_m)), w)
    c = answer.refined_confidence
    keep = (c > 0) & (w > 0)
    means = np.concatenate([answer.centres, answer.refined[keep]])
    sigmas = np.concatenate([np.full(len(w), float(tile_sigma_m)), np.full(int(keep.sum()), float(refined_sigma_m))])
    weights = np.concatenate([w * (1 - c), (w * c)[keep]])
    live = weights > 0
    return GaussianMixture(means[live], sigmas[live], weights[live] / weights[live].sum())
