"""Rendered routes with their truth, answered by a Localizer: the RouteCases that tools/evaluate_routes.py scores and
tools/fit_route_filter.py fits q on (geoloc/sequence/route_scores.py, fit.py).

A routes folder is what `python -m geoloc.synthetic.routes` writes, or the same layout from elsewhere:
ROUTES/<group>/route_NNNN/ with the frames (images, in name order), odometry.csv (one row per frame) and truth.csv
(one row per frame with the gallery's position keys: lat, lon or x_m, y_m). Route NNNN of every group is selected
by its number, so held-out routes (25-49, say) and test routes (0-24) of one folder never share a frame.
"""

from __future__ import annotations

import re
from collections.abc import Collection
from dataclasses import fields
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from geoloc.apps.localize.command import images_of
from geoloc.apps.localize.route import RoutePlane, truth_of
from geoloc.config import ConfigError, checked
from geoloc.data.io import read_rgb
from geoloc.gallery import POSITION_KEYS
from geoloc.sequence.odometry import ODOMETRY_FILE, read_odometry
from geoloc.sequence.particle_filter import FilterConfig
from geoloc.sequence.route_scores import RouteCase

ROUTE_NAME = re.compile(r"route_(\d+)")


def parse_ids(text: str) -> list[int]:
    """'0-24' or '3,5,10-12' -> the route numbers (ValueError naming the text otherwise)."""
    ids: list[int] = []
    for part in text.split(","):
        match = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if match is None or (match[2] is not None and int(match[2]) < int(match[1])):
            raise ValueError(f"route numbers {text!r}: give numbers and ranges like '0-24' or '3,5,10-12'")
        ids += range(int(match[1]), int(match[2] or match[1]) + 1)
    return ids


def filter_config(settings: list[str]) -> FilterConfig:
    """route.KEY=VALUE strings -> FilterConfig, checked as localize.py checks its route.* keys (geoloc.config.checked:
    an unknown key, a wrong type or a value out of range is refused, naming it)."""
    outside = [setting for setting in settings if not setting.startswith("route.") or "=" not in setting]
    try:
        if outside:
            raise ConfigError(f"{', '.join(map(repr, outside))} is not a route.* setting")
        return checked(OmegaConf.from_dotlist(settings).get("route", {}), FilterConfig, "route")
    except ConfigError as err:
        raise ConfigError(f"give route.KEY=VALUE with KEY one of {', '.join(f.name for f in fields(FilterConfig))}: "
                          f"{err}") from None


def route_folders(routes: Path, ids: Collection[int] | None = None) -> list[Path]:
    """routes/<group>/route_NNNN folders, by group then number, only those numbered in `ids` (None: all);
    FileNotFoundError naming the folder when none is."""
    found = sorted((folder.parent.name, int(match[1]), folder) for folder in Path(routes).glob("*/route_*")
                   if folder.is_dir() and (match := ROUTE_NAME.fullmatch(folder.name))
                   and (ids is None or int(match[1]) in ids))
    if not found:
        which = "" if ids is None else " with those numbers"
        raise FileNotFoundError(f"{routes} holds no <group>/route_NNNN folders{which}: give the routes folder "
                                "(python -m geoloc.synthetic.routes writes ROOT/routes)")
    return [folder for _, _, folder in found]


def route_case(localizer, plane: RoutePlane, folder: Path, query) -> RouteCase:
    """One route folder answered frame by frame (`query`: the localizer's parsed settings) as a RouteCase on
    `plane`; each frame's own answer is its refined top-1 where the refiner ran, else its top-1 tile."""
    frames = images_of(folder)
    odometry = read_odometry(folder / ODOMETRY_FILE)
    truth = truth_of(folder, plane)
    if truth is None or len(truth) != len(frames) or len(odometry) != len(frames):
        raise ValueError(f"{folder}: a route needs one odometry.csv row and one truth.csv row (with the gallery's "
                         f"position keys {POSITION_KEYS[plane.kind]}) per frame; it has {len(frames)} frames, "
                         f"{len(odometry)} odometry rows and {'no usable truth.csv' if truth is None else len(truth)}")
    keys = POSITION_KEYS[plane.kind]
    answers, single = [], []
    for frame in frames:
        result = localizer.localize(read_rgb(frame), query)
        answers.append(plane.answer(result))
        own = result.refined_position or result.position
        single.append(plane.to_plane([own[k] for k in keys], result.topk[0]["row"]))
    return RouteCase(answers, odometry, truth, np.stack(single))
