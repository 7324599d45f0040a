"""Methods plugged into the engine: `crossview` (MSAE cross-view geo-localization) and `mmdip` (dynamic scenes).

This package declares the `task` kind (`task.name`, and `task.module` for a task from outside geoloc). A task is
any object with `train(cfg, run_dir) -> metrics` and `evaluate(cfg, state) -> metrics`; each package here
registers itself (its own module is the object). They are found, not listed: the first lookup of a task imports
every package under geoloc/tasks/, so a new task is a new folder and nothing else names it.
"""

from __future__ import annotations

import importlib
import pkgutil

from geoloc import registry


def _import_task_packages() -> None:
    for found in pkgutil.iter_modules(__path__, prefix=f"{__name__}."):
        if found.ispkg:
            importlib.import_module(found.name)


registry.declare("task", section="task", load=_import_task_packages)
