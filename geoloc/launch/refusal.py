"""A refusal ends a run with one clear line on stderr and exit status 1, not Hydra's "Error executing job" and a
traceback.

    @hydra.main(...)
    def main(cfg):
        with refusals_in_one_line():
            evaluate(cfg)

A refusal is an error geoloc raises on purpose, whose message says what is wrong and what to do (ConfigError,
RunDirTaken), or a missing file (FileNotFoundError names it: a checkpoint, an image, a dataset). Any other error keeps Hydra's report. `HYDRA_FULL_ERROR=1` keeps the whole traceback for refusals
too. A refused run's Hydra folder is removed when it holds nothing of the run's own (geoloc/launch/rundir.py).
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from geoloc.config import ConfigError
from geoloc.launch.rundir import RunDirTaken, holds_nothing, is_cwd_or_above

REFUSALS = (ConfigError, RunDirTaken, FileNotFoundError)


@contextlib.contextmanager
def refusals_in_one_line() -> Iterator[None]:
    try:
        yield
    except REFUSALS as err:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        _remove_empty_run_dir()
        # SystemExit passes Hydra's job runner untouched: Python prints the line and exits with status 1
        raise SystemExit(f"{type(err).__name__}: {err}") from None


def _remove_empty_run_dir() -> None:
    """Hydra's folder of this run, when the run was refused before it wrote anything there."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    if run_dir.is_dir() and holds_nothing(run_dir) and not is_cwd_or_above(run_dir):
        shutil.rmtree(run_dir, ignore_errors=True)
