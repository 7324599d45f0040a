"""The run's own log: what a run prints (the epoch lines, the final table, localize.py's answers) is also written
to `<run_dir>/<job>.log` (train.log, evaluate.log, localize.log), the file Hydra's job logging writes its log
records to, so the run folder holds what the console showed.

Only stdout is copied: the progress bars (tqdm, on stderr) would fill the file with carriage returns. Both writers
append and flush each write, so the file keeps the order in which lines were written.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

from geoloc.engine.distributed import launch_rank


class _Tee:
    """A text stream that writes to the console stream and to the log file."""

    def __init__(self, console: TextIO, log: TextIO):
        self.console, self.log = console, log

    def write(self, text: str) -> int:
        self.log.write(text)
        self.log.flush()
        return self.console.write(text)

    def flush(self) -> None:
        self.log.flush()
        self.console.flush()

    def __getattr__(self, name):  # isatty, encoding, fileno, ...: the console's
        return getattr(self.console, name)


def log_path(run_dir: str | Path, job: str) -> Path:
    """`<run_dir>/<Hydra's job name>.log` under Hydra (the file its job logging writes), else `<run_dir>/<job>.log`."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        job = HydraConfig.get().job.name
    return Path(run_dir) / f"{job}.log"


@contextlib.contextmanager
def run_log(run_dir: str | Path | None, job: str) -> Iterator[Path | None]:
    """Copy stdout into the run's log for the block (rank 0 only: the other ranks of a launch write nothing)."""
    if run_dir is None or launch_rank() > 0:
        yield None
        return
    path = log_path(run_dir, job)
    console = sys.stdout
    with open(path, "a", encoding="utf-8") as log:
        sys.stdout = _Tee(console, log)
        try:
            yield path
        finally:
            sys.stdout = console
