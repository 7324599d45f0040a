"""Query views of one training pair: what the query branch sees of a street panorama while training. This module
declares the `query_views` kind (config section `views`) and registers its built-ins.

A factory returns None (`single`: the data module's one query, as configured by dataset.fov / random_heading) or
an object called as views(panorama, rng) -> (the main view's canvas, [extra canvases]): H×W×3 canvases of the
north-aligned, already flipped / turned panorama, each at the panorama's width with the unseen columns 0
(views.north_window). The main canvas is the training query; the extras go through the query branch too and reach
the loss as `query_views` (B×V×D, geoloc/tasks/crossview/task.py), so a loss that names them can compare them.

`any_view` draws a field of view f ~ U[fov_min, fov_max] (f = 360 with probability `full_share`) and a bearing
h ~ U[0, 360) per sample; its extras are, in this order:
- the same window placed at a wrong bearing h + d, d ~ U[min_offset, 360 - min_offset] (a negative for the pair:
  at evaluation the query is searched over headings, so its wrong placements must score below the true one);
- the full panorama (ConGeo, Mi et al. ECCV 2024: the limited view's descriptor is drawn to the full view's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geoloc.config import ConfigError
from geoloc.registry import declare, register
from geoloc.tasks.crossview.views import check_fov, north_window

declare("query_views", section="views")

#: the extras of `any_view`, in the order the loss receives them (geoloc/losses/any_view.py reads these indices)
WRONG_HEADING, FULL_VIEW = 0, 1


@register("query_views", "single")
def single() -> None:
    """The data module's one query view (dataset.fov, dataset.random_heading): no extra view is encoded."""
    return None


@dataclass(frozen=True)
class AnyView:
    fov_min: float = 70.0
    fov_max: float = 360.0
    full_share: float = 0.25
    min_offset: float = 20.0

    def __call__(self, panorama: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, list[np.ndarray]]:
        fov = 360.0 if rng.uniform() < self.full_share else float(rng.uniform(self.fov_min, self.fov_max))
        heading = float(rng.uniform(0.0, 360.0))
        offset = float(rng.uniform(self.min_offset, 360.0 - self.min_offset))
        main = north_window(panorama, fov, heading)
        # the same view placed at heading + offset: a heading change is a circular shift of the canvas's columns
        # (column j looks along 180 + 360 j / W degrees)
        wrong = np.roll(main, int(round(offset / 360.0 * panorama.shape[1])), axis=1)
        return main, [wrong, panorama]


@register("query_views", "any_view")
def any_view(fov_min: float = 70.0, fov_max: float = 360.0, full_share: float = 0.25,
             min_offset: float = 20.0) -> AnyView:
    """Random field of view in [fov_min, fov_max] (360 with probability full_share) at a random bearing, with the
    same window at a wrong bearing (at least min_offset degrees off) and the full panorama as extra views."""
    check_fov(fov_min, "views.fov_min")
    check_fov(fov_max, "views.fov_max")
    if fov_min > fov_max:
        raise ConfigError(f"views.fov_min ({fov_min}) must not exceed views.fov_max ({fov_max})")
    if not 0.0 <= full_share <= 1.0:
        raise ConfigError(f"views.full_share must lie in [0, 1], got {full_share}")
    if not 0.0 < min_offset <= 180.0:
        raise ConfigError(f"views.min_offset must lie in (0, 180] degrees, got {min_offset}")
    return AnyView(float(fov_min), float(fov_max), float(full_share), float(min_offset))
