"""The sequence filter's q (route.wrong_answer_prob) and temperature for one checkpoint and gallery, fitted from the
gallery's held-out queries (queries.jsonl: the split's queries with their positions, as `evaluate.py gallery.save=`
writes them) answered like the route's frames will be (geoloc/sequence/fit.py; docs/sequence.md).

    python tools/fit_route_filter.py CKPT GALLERY [--topk 10] [--heading 0] [--radius 25] [--out fit.json]

Prints the overrides for localize.py (route.wrong_answer_prob=... route.temperature=...) and the counts they come
from. The queries must not be frames of the routes to be localised. Images are read under the gallery's root.
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from geoloc.apps.localize.localizer import Localizer
from geoloc.apps.localize.route import route_plane
from geoloc.data.io import read_rgb
from geoloc.sequence.fit import fit_answer_model
from geoloc.sequence.particle_filter import FilterConfig


def held_out_answers(localizer: Localizer, topk: int, heading: float | None):
    """(FrameAnswer list, truths (N, 2) on the route plane) for every query of the localizer's gallery
    (queries.jsonl, as read and checked with the gallery), its images read under the gallery's root."""
    places = localizer.places
    plane = route_plane(places, FilterConfig())
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
    p.add_argument("--topk", type=int, default=10, help="the top-k the routes will be answered with")
    p.add_argument("--heading", type=float, default=None, help="the queries' heading when the routes' is known")
    p.add_argument("--radius", type=float, default=25.0, help="metres: a tile centre this near the truth is right")
    p.add_argument("--out", type=Path, default=None, help="also write the fit as JSON here")
    args = p.parse_args(argv)
    localizer = Localizer.load(args.ckpt, str(args.gallery), device="cpu")
    answers, truths = held_out_answers(localizer, args.topk, args.heading)
    model = fit_answer_model(answers, truths, args.radius)
    print(f"{model.answers} held-out queries, {model.hits} with a tile within {model.radius_m:g} m in the top-"
          f"{args.topk}; {model.right_scores} near and {model.wrong_scores} other tiles' scores", file=sys.stderr)
    print(f"route.wrong_answer_prob={model.wrong_answer_prob:.4f} route.temperature={model.temperature:.4f}")
    if args.out is not None:
        args.out.write_text(json.dumps({**model.__dict__, "topk": args.topk, "ckpt": args.ckpt,
                                        "gallery": str(args.gallery)}, indent=2))


if __name__ == "__main__":
    main()
