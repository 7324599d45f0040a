"""Each metric declares its keys once, with the worst value of each; the "collapsed" result is derived from them.

A metric module declares a `KeySet` (recall.py: R@K and R@1%, the hit rate; average_precision.py: AP;
geo_error.py: the metre keys; the cross-view heading search: the heading keys). A run's plan is the list of key
sets it reports (`geoloc.eval.retrieval_metrics.metric_plan`); `guarded` returns either the computed metrics,
checked to hold exactly the plan's keys, or, when the reference descriptors have collapsed, the worst value of
every key of the plan: ties count in the query's favour, so a gallery collapsed onto one point would otherwise
score perfectly (geoloc.eval.descriptors).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable, Iterable, Mapping

from geoloc.eval.descriptors import COLLAPSE_SPREAD

__all__ = ["KeySet", "collapsed", "guarded"]


@dataclass(frozen=True)
class KeySet:
    """The keys one metric reports, in order, each with its worst value."""

    worst: Mapping[str, float]

    def mode(self, key: str) -> str:
        """"max" where a larger value of `key` is better, else "min": a share (recall, hit rate, AP, within X), whose
        worst value is 0, is better higher; an error (metres, degrees, ECE), whose worst is its largest, lower."""
        return "max" if self.worst[key] == 0.0 else "min"

    def values(self, computed: Mapping[str, float]) -> dict[str, float]:
        """``computed`` as plain floats in the declared order; a RuntimeError if its keys are not the declared ones."""
        if set(computed) != set(self.worst):
            raise RuntimeError(f"a metric computed keys {sorted(computed)} but declares {sorted(self.worst)}")
        return {key: float(computed[key]) for key in self.worst}


def collapsed(plan: Iterable[KeySet]) -> dict[str, float]:
    """The worst value of every key of the plan: what a collapsed gallery reports."""
    out: dict[str, float] = {}
    for keys in plan:
        out.update(keys.worst)
    return out


def guarded(compute: Callable[[], dict], reference_spread: float, plan: Iterable[KeySet]) -> dict:
    """``compute()``'s metrics (checked against the plan's keys) plus ``reference_spread``; on a collapse, the
    plan's worst values with a warning instead (``compute`` is then not called: an all-zero collapse could not be
    ranked at all)."""
    plan = list(plan)
    if reference_spread < COLLAPSE_SPREAD:
        warnings.warn(f"reference descriptors have collapsed (spread {reference_spread:.2e} < {COLLAPSE_SPREAD}): "
                      "every image maps to about one point, so the metrics are meaningless here and each is "
                      "reported at its worst value (recall 0)")
        metrics = collapsed(plan)
    else:
        metrics = compute()
        declared = collapsed(plan)
        if list(metrics) != list(declared):
            raise RuntimeError(f"the metrics computed keys {list(metrics)} but the plan declares {list(declared)}")
    metrics["reference_spread"] = reference_spread
    return metrics

