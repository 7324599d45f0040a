"""Compute the static-class pixel fractions r_c of a training split (MMDIP eq. 1) and store them with the data.

    python data_prep/class_fractions.py --root DIR [--split train] [--format dynamic|carla4] [--force]

Writes DIR/class_fractions.json: {"classes": [8 names], "fractions": [8 floats], "pixels": [8 counts], "source":
{format, split, class map, file count, fingerprint of the label files}}. Training does the same by itself at
start-up whenever the file is missing or no longer matches the label files (geoloc.data.label_census), so this
tool is only needed to prepare a read-only copy of a dataset, or to look at the numbers. `dynamic` reads
label_static/ of the split's rows; `carla4` reads the static seg panel of the authors' 4-panel PNGs (CARLA tags
mapped to the 8 classes). Without --force an up-to-date file is kept.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from geoloc.tasks.mmdip.datasets import STATIC_CLASSES  # noqa: E402
from geoloc.data.label_census import FILE_NAME  # noqa: E402
from geoloc.tasks.mmdip.readers import load_class_fractions  # noqa: E402


def main(argv=None) -> Path:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", type=Path, required=True)
    p.add_argument("--split", default="train")
    p.add_argument("--format", choices=("dynamic", "carla4"), default="dynamic")
    p.add_argument("--force", action="store_true", help="recount even when the stored file is up to date")
    args = p.parse_args(argv)
    fractions = load_class_fractions(args.root, args.format, args.split, force=args.force)
    out = args.root / FILE_NAME
    print(f"{out}: " + ", ".join(f"{c} {f:.4f}" for c, f in zip(STATIC_CLASSES, fractions)))
    return out


if __name__ == "__main__":
    main()
