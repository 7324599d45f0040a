"""Picture building blocks every figure shares: image grids, heat-map overlays, PNG writing (RGB arrays)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

def overlay(img: np.ndarray, mask: torch.Tensor) -> np.ndarray:
    m = mask.detach().float().cpu().numpy().squeeze()
    m = (m - m.min()) / (np.ptp(m) + 1e-8)
    heat = cv2.applyColorMap(cv2.resize((m * 255).astype(np.uint8), img.shape[1::-1]), cv2.COLORMAP_JET)
    return cv2.addWeighted(img, 0.55, cv2.cvtColor(heat, cv2.COLOR_BGR2RGB), 0.45, 0)


def fit_height(img: np.ndarray, h: int) -> np.ndarray:
    return cv2.resize(img, (max(1, round(img.shape[1] * h / img.shape[0])), h))


def grid(rows: list[list[np.ndarray]], h: int = 128, pad: int = 4) -> np.ndarray:
    lines = []
    for row in rows:
        tiles = [np.pad(fit_height(t, h), ((pad, pad), (pad, pad), (0, 0)), constant_values=255) for t in row]
        lines.append(np.concatenate(tiles, axis=1))
    width = max(line.shape[1] for line in lines)
    lines = [np.pad(line, ((0, 0), (0, width - line.shape[1]), (0, 0)), constant_values=255) for line in lines]
    return np.concatenate(lines, axis=0)


def save_png(path: Path, img: np.ndarray) -> None:
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
