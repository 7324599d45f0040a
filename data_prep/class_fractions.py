"""Compute the static-class pixel fractions r_c of a training split (MMDIP eq. 1) and store them with the data.

    python data_prep/class_fractions.py --root DIR [--split train] [--format dynamic|carla4] [--force]

Writes DIR/class_fractions.json as {"classes": [8 names], "fractions": [8 floats]}, the file the synthetic
generator writes itself. `dynamic` reads label_static/ of the split's rows; `carla4` reads the static seg panel
of the authors' 4-panel PNGs (CARLA tags mapped to the 8 classes).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from geoloc.data.dynamic import (STATIC_CLASSES, CarlaFourPanelDataset, DynamicDataset,  # noqa: E402
                                 class_fractions, read_label)


def compute(root: Path, split: str, fmt: str) -> list[float]:
    if fmt == "dynamic":
        ds = DynamicDataset(root, split, check="off")
        labels = (read_label(ds._path("label_static", s)) for s in ds.samples)
    else:
        ds = CarlaFourPanelDataset(root, split)
        labels = (ds[i]["label"].numpy() for i in range(len(ds)))
    return class_fractions(labels)


def main(argv=None) -> Path:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", type=Path, required=True)
    p.add_argument("--split", default="train")
    p.add_argument("--format", choices=("dynamic", "carla4"), default="dynamic")
    p.add_argument("--force", action="store_true", help="overwrite an existing class_fractions.json")
    args = p.parse_args(argv)
    out = args.root / "class_fractions.json"
    if out.exists() and not args.force:
        raise SystemExit(f"{out} exists; pass --force to recompute it")
    fractions = compute(args.root, args.split, args.format)
    out.write_text(json.dumps({"classes": list(STATIC_CLASSES), "fractions": fractions}, indent=1))
    print(f"wrote {out}: " + ", ".join(f"{c} {f:.4f}" for c, f in zip(STATIC_CLASSES, fractions)))
    return out


if __name__ == "__main__":
    main()
