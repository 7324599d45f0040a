"""`python -m geoloc.apps.mmdip_tables --out DIR [--tables I II III IV] [hydra overrides ...]`: the MMDIP paper's
Tables I-IV and figures on one dataset (geoloc/apps/mmdip_tables/tables.py says what each holds), from train.py's config
with task=mmdip and the overrides given."""

from __future__ import annotations

import argparse
from pathlib import Path

from omegaconf import OmegaConf

from geoloc.launch.hydra_hooks import compose_conf
from geoloc.apps.mmdip_tables.tables import make_tables


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m geoloc.apps.mmdip_tables", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--tables", nargs="+", default=["I", "II", "III", "IV"], choices=["I", "II", "III", "IV"])
    p.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. dataset.root=DIR task.segmentation.epochs=4")
    args = p.parse_args(argv)
    cfg = compose_conf("train", ["task=mmdip", f"run_dir={args.out}", *args.overrides])
    OmegaConf.resolve(cfg)
    make_tables(cfg, args.out, tuple(args.tables))


if __name__ == "__main__":
    main()
