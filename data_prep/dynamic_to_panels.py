"""Write a synthetic `dynamic` layout as the released panel formats, to run their readers and place protocols:

    python data_prep/dynamic_to_panels.py --root DYN --out DIR --format {carla4,emptycities} [--splits train val]

carla4       DIR/<split>/NNNNNNN.png = dynamic RGB | dynamic seg | static RGB | static seg, the segs as CARLA 0.8
             tags in all three channels (static class c -> its CARLA tag, vehicle -> 10, pedestrian -> 4), and
             DIR/class_fractions.json copied from DYN.
emptycities  DIR/<split>/NNNNNNN.png = dynamic RGB | static RGB | dynamic mask (0/255 in all three channels).

A panel file is its own place, so the train split keeps every row (both views of a place, for training and the
vocabulary) and every other split one view per place: its query row, which has traffic. The panels keep the
source size (not Empty Cities' 800x600; the reader says so and resizes to dataset.image_size).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from geoloc.tasks.mmdip.datasets import CARLA_TO_STATIC, DynamicDataset, read_label, read_rgb  # noqa: E402

# one CARLA 0.8 tag per static class (the inverse of CARLA_TO_STATIC on its first tag), then the two dynamic
# classes of label_dynamic: 8 vehicle -> tag 10, 9 pedestrian -> tag 4
STATIC_TO_CARLA = {c: min(t for t, s in CARLA_TO_STATIC.items() if s == c and t not in (4, 10)) for c in range(8)}
DYNAMIC_LABEL_TO_CARLA = np.array([STATIC_TO_CARLA[c] for c in range(8)] + [10, 4], np.uint8)


def _three(channel: np.ndarray) -> np.ndarray:
    return np.repeat(channel[..., None], 3, axis=2)


def panels(ds: DynamicDataset, sample: str, fmt: str) -> np.ndarray:
    """The RGB panel image of one sample of the dynamic layout."""
    dynamic, static = read_rgb(ds._path("rgb_dynamic", sample)), read_rgb(ds._path("rgb_static", sample))
    if fmt == "emptycities":
        mask = cv2.imread(str(ds._path("mask_dynamic", sample)), cv2.IMREAD_GRAYSCALE)
        return np.concatenate([dynamic, static, _three(np.where(mask > 0, 255, 0).astype(np.uint8))], axis=1)
    dyn_tags = DYNAMIC_LABEL_TO_CARLA[read_label(ds._path("label_dynamic", sample), num_classes=10)]
    sta_tags = DYNAMIC_LABEL_TO_CARLA[read_label(ds._path("label_static", sample))]
    return np.concatenate([dynamic, _three(dyn_tags), static, _three(sta_tags)], axis=1)


def convert(root: Path, out: Path, fmt: str, splits=("train", "val")) -> dict[str, int]:
    """Writes the panel folders; returns the number of files per split."""
    counts = {}
    for split in splits:
        roles = ("reference", "query") if split == "train" else ("query",)
        ds = DynamicDataset(root, split, roles=roles, check="exists")
        folder = out / split
        folder.mkdir(parents=True, exist_ok=True)
        for sample in ds.samples:
            cv2.imwrite(str(folder / f"{sample}.png"), cv2.cvtColor(panels(ds, sample, fmt), cv2.COLOR_RGB2BGR))
        counts[split] = len(ds.samples)
    if fmt == "carla4" and (root / "class_fractions.json").is_file():
        shutil.copy(root / "class_fractions.json", out / "class_fractions.json")
    (out / "panels_source.json").write_text(json.dumps({"source": str(root.resolve()), "format": fmt,
                                                        "files": counts}, indent=1) + "\n")
    return counts


def main(argv=None) -> dict[str, int]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", type=Path, required=True, help="a synthetic `dynamic` layout folder")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--format", choices=("carla4", "emptycities"), required=True)
    p.add_argument("--splits", nargs="+", default=["train", "val"])
    args = p.parse_args(argv)
    counts = convert(args.root, args.out, args.format, tuple(args.splits))
    print(f"wrote {args.format} panels to {args.out}: " + ", ".join(f"{s} {n}" for s, n in counts.items()))
    return counts


if __name__ == "__main__":
    main()
