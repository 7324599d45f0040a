"""Write a synthetic VIGOR dataset with one city under another sun or season (geoloc.synthetic.relight): the same
places, for the cross-area diagnosis in docs/datasets.md.

    python tools/relight_vigor.py ~/.cache/geoloc/synthetic/vigor-vigor_medium-seed0 /tmp/chicago_high_sun \\
        --city Chicago --sun-elevation 64 [--sun-azimuth DEG] [--season S] [--tiles-only]
"""
import argparse

from geoloc.synthetic.relight import relight_city


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("source", help="a complete synthetic vigor dataset geoloc rendered")
    p.add_argument("out", help="a new, empty folder")
    p.add_argument("--city", required=True)
    p.add_argument("--sun-elevation", type=float)
    p.add_argument("--sun-azimuth", type=float)
    p.add_argument("--season", type=float, help="0 summer .. 0.5 autumn .. 1 winter")
    p.add_argument("--tiles-only", action="store_true", help="keep the city's panoramas as they are")
    a = p.parse_args()
    out = relight_city(a.source, a.out, a.city, a.sun_elevation, a.sun_azimuth, a.season, panoramas=not a.tiles_only)
    print(out)


if __name__ == "__main__":
    main()
