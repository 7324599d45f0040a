"""Calibrated confidence: the probability that an answer is right, from the answer's own raw scores.

A `Calibrator` maps an answer's score features x (F,) to P(right | x) = sigmoid(w · (x - mean) / scale + b): a
logistic regression (Platt scaling, Platt 1999, with several features), fitted by Newton's method on labelled
answers that are not the test answers. What "right" means is the calibrator's `target` ("top1": the top-1
reference is the query's positive, by the scorer's rank rule; a metric-localisation method may fit "within_5m" from
its own score with the same call). Logistic rather than isotonic: two features (the top-1 score and its margin over
the second) enter together, the map is smooth and monotone in each, and five numbers store it.

Evaluation:
- `expected_calibration_error`: 15 equal-count bins of the confidences (sorted, then cut into 15 runs of
  n/15 answers); ECE = sum_b (n_b / n) |mean confidence_b - accuracy_b| (Guo et al., ICML 2017; equal-mass bins as
  in Nixon et al., 2019);
- `coverage_accuracy`: answers ranked by confidence, best first; keeping the first k gives coverage k/n and
  accuracy (right among them)/k.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from geoloc.eval.keys import KeySet

ECE_BINS = 15
# the ECE of the top-1 confidence, and of a refiner's P(within 5 m), on the scored queries; worst: 1
CALIBRATION_KEYS = KeySet({"ece_top1": 1.0, "ece_within_5m": 1.0})
RETRIEVAL_FEATURES = ("top1_score", "top1_margin")
RIDGE = 1e-3  # an L2 pull on the weights keeps them finite when the labels are separable
LOWEST_SCORE = -1.0  # cosine similarity of unit descriptors: a gallery of one reference has this as its second score

__all__ = ["CALIBRATION_KEYS", "Calibrator", "coverage_accuracy", "expected_calibration_error", "fit_calibrator",
           "retrieval_features"]


def retrieval_features(top_scores) -> np.ndarray:
    """(Q, k) scores of each query's top-k references, best first -> (Q, 2) [top-1 score, top-1 minus top-2]."""
    s = np.asarray(top_scores, np.float64)
    if s.ndim != 2 or s.shape[1] < 1:
        raise ValueError(f"top_scores must be Q x k (k >= 1) scores, best first; got shape {s.shape}")
    second = s[:, 1] if s.shape[1] > 1 else np.full(len(s), LOWEST_SCORE)
    second = np.where(np.isfinite(second), second, LOWEST_SCORE)  # a short candidate list ends in -inf
    return np.stack([s[:, 0], s[:, 0] - second], axis=1)


def _sigmoid(z: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * z))  # exact and overflow-free for any z


@dataclass
class Calibrator:
    """P(right | x) = sigmoid(weights · (x - mean) / scale + bias); x holds the named `features`.
    `condition`: what answers it was fitted on (e.g. the heading known); `fitted_on`: how many answers, how many
    right, and the rule that picked them."""

    target: str
    features: tuple[str, ...]
    mean: list[float]
    scale: list[float]
    weights: list[float]
    bias: float
    condition: dict = field(default_factory=dict)
    fitted_on: dict = field(default_factory=dict)

    def __post_init__(self):
        self.features = tuple(self.features)
        sizes = {len(self.features), len(self.mean), len(self.scale), len(self.weights)}
        if len(sizes) != 1:
            raise ValueError(f"calibrator {self.target!r}: features, mean, scale and weights differ in length")
        numbers = [*self.mean, *self.scale, *self.weights, self.bias]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in numbers):
            raise ValueError(f"calibrator {self.target!r}: mean, scale, weights and bias must be finite numbers")
        if min(self.scale) <= 0:
            raise ValueError(f"calibrator {self.target!r}: scale must be positive, got {self.scale}")

    def probability(self, x) -> np.ndarray:
        """(n, F) features -> (n,) probabilities in [0, 1]."""
        x = np.asarray(x, np.float64)
        if x.ndim != 2 or x.shape[1] != len(self.features):
            raise ValueError(f"calibrator {self.target!r} takes n x {len(self.features)} features "
                             f"{self.features}, got shape {x.shape}")
        z = ((x - np.array(self.mean)) / np.array(self.scale)) @ np.array(self.weights) + self.bias
        return _sigmoid(z)

    def to_json(self) -> dict:
        return {**asdict(self), "features": list(self.features)}

    @classmethod
    def from_json(cls, record: dict, where: str = "the calibration") -> "Calibrator":
        """A record written by to_json; a ValueError naming `where` and what is wrong otherwise."""
        try:
            return cls(**record)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{where} is not a calibrator record: {err}") from None


def fit_calibrator(features, correct, target: str, names=RETRIEVAL_FEATURES, condition: dict | None = None,
                   rule: str = "", iterations: int = 50) -> Calibrator:
    """Fit P(correct | features) by L2-regularised logistic regression (Newton's method on standardised features).

    features: (n, F); correct: (n,) bool (whether each answer was right); names: the F feature names."""
    x = np.asarray(features, np.float64)
    y = np.asarray(correct, bool).astype(np.float64)
    if x.ndim != 2 or x.shape[1] != len(names) or y.shape != (x.shape[0],):
        raise ValueError(f"features must be n x {len(names)} and correct (n,); got {x.shape} and {y.shape}")
    if len(y) < 2 or not np.isfinite(x).all():
        raise ValueError(f"a calibrator needs at least 2 answers with finite features, got {len(y)}")
    mean, scale = x.mean(0), x.std(0)
    scale = np.where(scale > 1e-12, scale, 1.0)
    z = np.concatenate([(x - mean) / scale, np.ones((len(y), 1))], axis=1)
    theta = np.zeros(z.shape[1])
    penalty = RIDGE * len(y) * np.r_[np.ones(x.shape[1]), 0.0]  # the bias is not pulled
    for _ in range(iterations):
        p = _sigmoid(z @ theta)
        gradient = z.T @ (p - y) + penalty * theta
        hessian = (z * (p * (1 - p))[:, None]).T @ z + np.diag(penalty + 1e-9)
        step = np.linalg.solve(hessian, gradient)
        theta -= step
        if np.abs(step).max() < 1e-10:
            break
    return Calibrator(target, tuple(names), mean.tolist(), scale.tolist(), theta[:-1].tolist(), float(theta[-1]),
                      condition or {}, {"answers": int(len(y)), "right": int(y.sum()), "rule": rule})


def _checked(confidence, correct) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(confidence, np.float64)
    y = np.asarray(correct, bool)
    if p.ndim != 1 or p.shape != y.shape or len(p) == 0:
        raise ValueError(f"confidence and correct must be two (n,) arrays, n >= 1; got {p.shape} and {y.shape}")
    if not (np.isfinite(p).all() and (p >= 0).all() and (p <= 1).all()):
        raise ValueError("confidence must hold probabilities in [0, 1]")
    return p, y


def expected_calibration_error(confidence, correct, bins: int = ECE_BINS) -> float:
    """ECE over `bins` equal-count bins: the answers sorted by confidence (stable), cut into `bins` runs whose sizes
    differ by at most one (numpy.array_split), each run's |mean confidence - accuracy| weighted by its share."""
    p, y = _checked(confidence, correct)
    order = np.argsort(p, kind="stable")
    return float(sum(len(b) / len(p) * abs(p[b].mean() - y[b].mean())
                     for b in np.array_split(order, min(bins, len(p)))))


def coverage_accuracy(confidence, correct) -> tuple[np.ndarray, np.ndarray]:
    """(coverage (n,), accuracy (n,)): keeping the k most confident answers (ties in their given order) gives
    coverage k/n and accuracy = right among them / k, for k = 1..n."""
    p, y = _checked(confidence, correct)
    order = np.argsort(-p, kind="stable")
    kept = np.arange(1, len(p) + 1)
    return kept / len(p), np.cumsum(y[order]) / kept
