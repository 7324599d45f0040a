"""The sequence filter's q (route.wrong_answer_prob) and temperature for one checkpoint and gallery, fitted from the
gallery's held-out queries (queries.jsonl: the split's queries with their positions, as `evaluate.py gallery.save=`
writes them) answered like the route's frames will be (geoloc/sequence/fit.py; docs/sequence.md). With --routes,
the filter's settings are then chosen on held-out routes (fit_route_settings): of a grid (by default q alone), the
setting with the smallest median 95% region among those whose region holds the truth at the last frame on at least
95% of them; the temperature stays the queries' fit.

    python tools/fit_route_filter.py CKPT GALLERY [--topk 10] [--heading 0] [--radius 25] [--out fit.json]
        [--routes ROUTES --ids 25-49 [--grid wrong_answer_prob=0.5,0.8 tile_sigma_m=25,35]]
        [route.KEY=VALUE ...]

Prints the overrides for localize.py (route.wrong_answer_prob=... route.temperature=...) and the counts they come
from. The queries and the held-out routes must not be frames of the routes to be localised. Images are read under
the gallery's root. route.KEY=VALUE sets the rest of the filter for the route fit (the odometry's noise, say); a
route.temperature given is kept instead of fitted (where the scores do not rank the tiles, say).
"""

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

from geoloc.apps.localize.localizer import Localizer
from geoloc.apps.localize.route import route_plane
from geoloc.apps.localize.route_cases import filter_config, parse_ids, route_case, route_folders
from geoloc.data.io import read_rgb
from geoloc.sequence.fit import ROUTE_GRID, fit_answer_model, fit_route_settings


def held_out_answers(localizer: Localizer, plane, topk: int, heading: float | None):
    """(FrameAnswer list, truths (N, 2) on the route plane) for every query of the localizer's gallery
    (queries.jsonl, as read and checked with the gallery), its images read under the gallery's root."""
    places = localizer.places
    query = localizer.parse(topk=topk, heading=heading)
    answers, truths = [], []
    for path, line in places.queries.items():
        result = localizer.localize(read_rgb(places.root / path), query)
        answers.append(plane.answer(result))
        truths.append(plane.to_plane(places.position_of(line)))
    return answers, np.stack(truths)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("ckpt")
    p.add_argument("gallery", type=Path)
    p.add_argument("settings", nargs="*", help="route.KEY=VALUE: the rest of the filter, for the route fit")
    p.add_argument("--topk", type=int, default=10, help="the top-k the routes will be answered with")
    p.add_argument("--heading", type=float, default=None, help="the queries' heading when the routes' is known")
    p.add_argument("--radius", type=float, default=25.0, help="metres: a tile centre this near the truth is right")
    p.add_argument("--routes", type=Path, default=None, help="a routes folder whose held-out routes choose q")
    p.add_argument("--ids", default=None, help="with --routes: the held-out route numbers, e.g. 25-49")
    p.add_argument("--grid", nargs="+", default=[f"{k}={','.join(map(str, v))}" for k, v in ROUTE_GRID.items()],
                   help="with --routes: FilterConfig fields and the values to try, NAME=v1,v2,...")
    p.add_argument("--out", type=Path, default=None, help="also write the fit as JSON here")
    args = p.parse_intermixed_args(argv)
    if args.routes is not None and args.ids is None:
        p.error("--routes needs --ids: the held-out routes' numbers, none of them a route to be evaluated")
    config = filter_config(args.settings)
    localizer = Localizer.load(args.ckpt, str(args.gallery), device="cpu")
    plane = route_plane(localizer.places, config)
    answers, truths = held_out_answers(localizer, plane, args.topk, args.heading)
    given = any(setting.startswith("route.temperature=") for setting in args.settings)
    model = fit_answer_model(answers, truths, args.radius, config.temperature if given else None)
    print(f"{model.answers} held-out queries, {model.hits} with a tile within {model.radius_m:g} m in the top-"
          f"{args.topk}; {model.right_scores} near and {model.wrong_scores} other tiles' scores", file=sys.stderr)
    record = {**model.__dict__, "topk": args.topk, "ckpt": args.ckpt, "gallery": str(args.gallery)}
    q, temperature, extra = model.wrong_answer_prob, model.temperature, ""
    if args.routes is not None:
        query = localizer.parse(topk=args.topk, heading=args.heading)
        cases = [route_case(localizer, plane, folder, query)
                 for folder in route_folders(args.routes, parse_ids(args.ids))]
        grid = {}
        for item in args.grid:
            name, _, values = item.partition("=")
            grid[name] = [float(v) for v in values.split(",") if v]
        fit = fit_route_settings(cases, plane.extent, model.applied(config), grid)
        for settings, scores in fit.scores:
            print(f"{settings}: the region holds the truth on {scores.region:.1%} of {scores.routes} held-out routes, "
                  f"the last frame within 25 m on {scores.last:.1%}", file=sys.stderr)
        if not fit.calibrated:
            print(f"no setting reached {fit.level:.0%}: the one covering most is given; widen the grid",
                  file=sys.stderr)
        q, temperature = fit.settings.get("wrong_answer_prob", q), fit.settings.get("temperature", temperature)
        extra = " ".join(f"route.{k}={v:g}" for k, v in fit.settings.items()
                         if k not in ("wrong_answer_prob", "temperature"))
        record.update(route_settings=fit.settings, route_calibrated=fit.calibrated, route_ids=args.ids,
                      routes=str(args.routes), route_scores=[{**s, **asdict(v)} for s, v in fit.scores])
    print(f"route.wrong_answer_prob={q:.4f} route.temperature={temperature:.4f}" + (" " + extra if extra else ""))
    if args.out is not None:
        args.out.write_text(json.dumps(record, indent=2))


if __name__ == "__main__":
    main()
