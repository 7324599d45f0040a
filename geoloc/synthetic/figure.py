"""The README picture: an aerial tile, its panorama, and a static/dynamic perspective pair with labels.

    python -m geoloc.synthetic.figure docs/synthetic_example.png [--seed 0] [--index 3]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from .classes import colorize
from .world_config import resolve
from .samples import render_pair, render_place_views


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.rectangle(out, (0, 0), (8 + 7 * len(text), 16), (0, 0, 0), -1)
    cv2.putText(out, text, (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def example_figure(seed: int = 0, index: int = 3, style: str = "suburban") -> np.ndarray:
    """-> RGB uint8 image (about 1000 px wide)."""
    pair_cfg, _ = resolve("cvusa", "small", {"style": style})
    pair = render_pair(pair_cfg, seed, "train", index, sphere=False)
    aerial = _label(cv2.resize(pair["aerial"], (224, 224), interpolation=cv2.INTER_AREA),
                    "aerial (north up)")
    pano = cv2.resize(pair["pano"], (784, 142), interpolation=cv2.INTER_AREA)
    pano_lab = cv2.resize(colorize(pair["pano_labels"]), (784, 82), interpolation=cv2.INTER_NEAREST)
    pano = np.concatenate([_label(pano, "panorama: S | W | N | E | S"), pano_lab], 0)
    top = np.concatenate([aerial, pano], 1)

    view_cfg, _ = resolve("dynamic", "dynamic_small", {"style": "urban", "view_size": 196})
    views = render_place_views(view_cfg, seed, "train", index)
    ref = views[0]
    tiles = [
        _label(ref["rgb_dynamic"], "dynamic"),
        _label(colorize(ref["label_dynamic"]), "dynamic labels"),
        _label(ref["rgb_static"], "static"),
        _label(colorize(ref["label_static"]), "static labels"),
        _label(np.dstack([ref["mask_dynamic"]] * 3), "dynamic mask"),
    ]
    bottom = np.concatenate(tiles, 1)
    w = max(top.shape[1], bottom.shape[1])
    pad = lambda a: np.pad(a, ((0, 0), (0, w - a.shape[1]), (0, 0)), constant_values=255)  # noqa: E731
    return np.concatenate([pad(top), np.full((6, w, 3), 255, np.uint8), pad(bottom)], 0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--index", type=int, default=3)
    a = p.parse_args()
    img = example_figure(a.seed, a.index)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(a.out, img[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(a.out, img.shape, Path(a.out).stat().st_size // 1024, "KB")


if __name__ == "__main__":
    main()
