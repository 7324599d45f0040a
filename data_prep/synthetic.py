"""Generate a synthetic dataset: python data_prep/synthetic.py --layout {cvusa,cvact,dynamic,vigor,u1652} --out DIR

Sizes and appearance-gap controls default to the preset's; see docs/synthetic.md.
"""
import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from geoloc.synthetic import LAYOUTS, PRESETS, generate  # noqa: E402
from geoloc.synthetic.world_config import FIELDS, OPTION_FIELDS, OPTIONS, SynthConfig  # noqa: E402

HELP = {
    "gap_strength": "appearance gap between the two views of a place, 0..1 (0.5 moderate)",
    "sun_shift": "largest sun azimuth change between views, degrees",
    "color_shift": "std of per-channel log gain / exposure per view",
    "season_shift": "largest vegetation season change (0 summer .. 1 bare winter)",
    "traffic_change": "fraction of cars/pedestrians that differ between views",
    "noise_std": "sensor noise std, 8-bit levels",
    "jpeg_quality": "lowest JPEG quality a view is saved at",
    "view_nuisance": "cvusa, cvact: strength 0..1 of the nuisances drawn apart per view (materials, gamma, haze, "
                     "tile scale, camera height and pitch); default none",
    "style": "terrain: mix | urban | suburban | rural",
    "cities": "vigor: how many of VIGOR's cities (Chicago, NewYork, SanFrancisco, Seattle, in that order)",
    "grid": "vigor: satellite tiles per side of a city",
    "drone_views": "u1652: drone views per building",
    "extra_gallery": "u1652: gallery-only (distractor) buildings in test",
}
COUNTS = "pairs (cvusa, cvact), places (dynamic), panoramas per city (vigor) or buildings (u1652)"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--layout", required=True, choices=LAYOUTS)
    p.add_argument("--out", required=True, help="output directory (new, empty, or an earlier run's)")
    p.add_argument("--train", type=int, default=None, help=f"train {COUNTS}; default: preset's")
    p.add_argument("--val", type=int, default=None, help=f"val {COUNTS} (vigor, u1652: test); default: preset's")
    p.add_argument("--seed", type=int, default=0, help="default 0")
    p.add_argument("--preset", default=None, choices=sorted(PRESETS), help="default: the layout's full size")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default 1); output is the same")
    p.add_argument("--no-progress", action="store_true")
    defaults = SynthConfig()
    for name in FIELDS:
        kind = type(getattr(defaults, name))
        kind = {type(None): float}.get(kind, kind)
        if name == "jpeg_quality":
            kind = int
        p.add_argument("--" + name.replace("_", "-"), dest=name, type=kind, default=None,
                       help=HELP.get(name, f"default {getattr(defaults, name)!r} or the preset's"))
    for layout, names in OPTION_FIELDS.items():
        for name in names:
            default = getattr(OPTIONS[layout](), name)
            p.add_argument("--" + name.replace("_", "-"), dest=name, type=int, default=None,
                           help=HELP.get(name, layout) + f" (default {default} or the preset's)")
    a = p.parse_args(argv)
    names = list(FIELDS) + [n for names in OPTION_FIELDS.values() for n in names]
    overrides = {k: getattr(a, k) for k in names if getattr(a, k) is not None}
    try:
        out = generate(a.layout, a.out, a.train, a.val, seed=a.seed, preset=a.preset, workers=a.workers,
                       progress=not a.no_progress, **overrides)
    except (ValueError, TypeError, OSError, RuntimeError) as err:
        p.exit(2, f"error: {err}\n")
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
