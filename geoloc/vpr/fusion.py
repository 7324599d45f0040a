"""Fused similarity of MMDIP eq. 5 and the gallery of reference codes.

M(q, r) = alpha * cos(BoW_q, BoW_r) + (1 - alpha) * cos(SPM_q, SPM_r), alpha = 0.5.

`fused_descriptors` turns the two codes into one unit vector per image whose query-reference dot product is
exactly M: [sqrt(alpha) bow/|bow|, sqrt(1-alpha) spm/|spm|, pad_query, pad_reference]. A zero code (no ORB
keypoints) leaves its block at zero; the pad column of the image's role takes the missing norm, and the two pad
columns never meet (queries pad one, references the other), so M is unchanged and every row has norm 1. That lets
the project's scorer (geoloc.eval.scoring: distance 2 - 2 a.b on unit vectors) rank by M, as recall and the
gallery search do.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from geoloc.eval.scoring import top_k


def l2_normalize(x: np.ndarray) -> np.ndarray:
    """Row-wise L2 normalisation; zero rows stay zero (no NaN)."""
    x = np.asarray(x, dtype=np.float32)
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, norm, out=np.zeros_like(x), where=norm > 0)


def fused_similarity(q_bow, q_spm, r_bow, r_spm, alpha: float = 0.5) -> np.ndarray:
    """Nq x Nr matrix of eq. 5."""
    bow = l2_normalize(q_bow) @ l2_normalize(r_bow).T
    spm = l2_normalize(q_spm) @ l2_normalize(r_spm).T
    return alpha * bow + (1 - alpha) * spm


def fused_descriptors(bow: np.ndarray, spm: np.ndarray, alpha: float, role: str) -> np.ndarray:
    """N x (K + D + 2) unit rows whose query.reference dot product is eq. 5's M."""
    if role not in ("query", "reference"):
        raise ValueError(f"role must be 'query' or 'reference', got {role!r}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must lie in [0, 1], got {alpha}")
    b = np.sqrt(alpha) * l2_normalize(bow)
    s = np.sqrt(1 - alpha) * l2_normalize(spm)
    pad = np.zeros((len(b), 2), np.float32)
    norm2 = (b**2).sum(1) + (s**2).sum(1)
    pad[:, 0 if role == "query" else 1] = np.sqrt(np.clip(1 - norm2, 0, None))
    return np.concatenate([b, s, pad], axis=1)


@dataclass
class Gallery:
    """Reference codes saved once so queries do not recompute them: BoW (N x K), SPM (N x D), place ids."""

    bow: np.ndarray
    spm: np.ndarray
    places: np.ndarray
    levels: int

    def save(self, path: str | Path) -> None:
        np.savez(path, bow=self.bow, spm=self.spm, places=self.places, levels=self.levels)

    @classmethod
    def load(cls, path: str | Path) -> "Gallery":
        with np.load(path) as f:
            return cls(f["bow"], f["spm"], f["places"], int(f["levels"]))

    def search(self, q_bow: np.ndarray, q_spm: np.ndarray, alpha: float = 0.5, k: int = 10) -> np.ndarray:
        """Place ids of the top-k references of each query by eq. 5 (the scorer's top-k of the fused
        descriptors: the lower gallery row first among equal scores)."""
        query = torch.from_numpy(fused_descriptors(q_bow, q_spm, alpha, "query"))
        reference = torch.from_numpy(fused_descriptors(self.bow, self.spm, alpha, "reference"))
        return self.places[top_k(query, reference, k)[1].numpy()]
