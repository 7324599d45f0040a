"""The keys a cross-view run's validation reports (CrossViewTask.validation_epoch_end), as key sets
(geoloc.eval.keys): from the config alone, every key some split could give, and once the validation split is read,
exactly its keys. trainer.monitor is checked against both, at the parse and before the first epoch, so a misspelt
metric fails at the start of a run instead of after its first validation (which a refinement recipe runs after 15
epochs), when the run's folder already holds its log.
"""

from __future__ import annotations

from geoloc.config import ConfigError
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.keys import KeySet, collapsed
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.refine import RefineConfig, fine_plan
from geoloc.tasks.crossview.validation import HeadingSearch, Retrieval, protocol

SPREAD = "reference_spread"  # reported beside every plan (geoloc.eval.keys.guarded)


def validation_plan(data: CrossViewDataConfig, refine: RefineConfig | None,
                    split: RetrievalSplit | None = None) -> list[KeySet]:
    """The key sets validation reports on `split` for this dataset config and refiner (None: retrieval alone);
    split=None: every set some split could give (hit rate with semi-positives, AP with labels, metres with
    positions)."""
    plan = protocol(data.random_heading).plan(split)  # the protocol CrossViewTask.validate_on chooses
    return plan + (fine_plan(split, refine) if refine is not None else [])


def check_monitor(monitor: str, plan: list[KeySet], where: str) -> None:
    """ConfigError naming trainer.monitor and the keys `plan` reports (`where`: of what), unless it is one of them."""
    keys = [*collapsed(plan), SPREAD]
    if monitor not in keys:
        raise ConfigError(f"trainer.monitor={monitor!r} is not a metric that validation reports {where}: it reports "
                          f"{', '.join(keys)}. Give one of them (with trainer.monitor_mode=min for an error in metres "
                          "or degrees)")


def known_mode(key: str) -> str | None:
    """"max" or "min", the better direction of a key some cross-view validation reports (KeySet.mode), or None for
    a key it never reports."""
    every = [*Retrieval().plan(None), *HeadingSearch().plan(None),
             *fine_plan(None, RefineConfig(orientation_noise_deg=180.0))]
    return next((keys.mode(key) for keys in every if key in keys.worst), None)
