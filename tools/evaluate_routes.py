"""The sequence filter on rendered routes with known truth, answered by one checkpoint against its saved gallery: the
figures of docs/sequence.md's tables (geoloc/sequence/route_scores.py says what each one is).

    python tools/evaluate_routes.py CKPT GALLERY ROUTES [--ids 0-24] [--topk 10] [--heading 0] [--seed 0]
        [--out scores.json] [route.KEY=VALUE ...]

ROUTES is a routes folder (`python -m geoloc.synthetic.routes ROOT` writes ROOT/routes); --ids picks route numbers
in every city (default: all). route.KEY=VALUE sets the filter as localize.py's route.* keys do (FilterConfig);
tools/fit_route_filter.py prints the fitted ones. Each frame is answered as localize.py answers it; route r (in
city, then number order) is filtered with seed --seed + r. Prints a markdown row and, with --out, writes the scores
and the settings as JSON.
"""

import argparse
import json
from dataclasses import asdict
from pathlib import Path

from geoloc.apps.localize.localizer import Localizer
from geoloc.apps.localize.route import route_plane
from geoloc.apps.localize.route_cases import filter_config, parse_ids, route_case, route_folders
from geoloc.sequence.route_scores import score_routes

ROW = ("routes", "single", "last", "ratio", "region", "region_ha", "ellipse", "ellipse_ha", "recover", "first_wrong",
       "ms_per_frame")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("ckpt")
    p.add_argument("gallery", type=Path)
    p.add_argument("routes", type=Path)
    p.add_argument("settings", nargs="*", help="route.KEY=VALUE: the filter's settings (FilterConfig)")
    p.add_argument("--ids", default=None, help="route numbers in every city, e.g. 0-24 (default: all)")
    p.add_argument("--topk", type=int, default=10)
    p.add_argument("--heading", type=float, default=None, help="the frames' heading when it is known (0: north up)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_intermixed_args(argv)
    config = filter_config(args.settings)
    folders = route_folders(args.routes, None if args.ids is None else parse_ids(args.ids))
    localizer = Localizer.load(args.ckpt, str(args.gallery), device="cpu")
    plane = route_plane(localizer.places, config)
    query = localizer.parse(topk=args.topk, heading=args.heading)
    cases = [route_case(localizer, plane, folder, query) for folder in folders]
    scores = score_routes(cases, plane.extent, config, lambda r: args.seed + r)
    values = {**asdict(scores), "ratio": scores.ratio}
    print("| " + " | ".join(ROW) + " |")
    print("| " + " | ".join(f"{values[k]:.3f}" if isinstance(values[k], float) else str(values[k]) for k in ROW) + " |")
    if args.out is not None:
        args.out.write_text(json.dumps({"scores": values, "route": asdict(config), "ids": args.ids, "topk": args.topk,
                                        "heading": args.heading, "ckpt": args.ckpt, "gallery": str(args.gallery),
                                        "routes": str(args.routes)}, indent=2))


if __name__ == "__main__":
    main()
