"""What the table apps (`geoloc robustness`, `geoloc bench`) share: their fovs= check, evaluate.py's config composed
as evaluate.py composes it, an out= folder checked before anything runs, and files written whole, never replaced
unasked."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from geoloc.config import ConfigError


def check_fovs(fovs: list[float]) -> None:
    """fovs= of a table app: a non-empty list of fields of view in degrees, each in (0, 360]."""
    if not fovs or any(not 0 < f <= 360 for f in fovs):
        raise ValueError(f"fovs must be a non-empty list of degrees in (0, 360], got {fovs}")


def evaluate_config(ckpt: str, overrides, device: str, num_workers: int, progress: bool):
    """evaluate.py's config for `overrides`, composed from geoloc/conf/evaluate.yaml as `python evaluate.py` composes it."""
    from geoloc.launch.hydra_hooks import compose_conf

    return compose_conf("evaluate", [f"ckpt={ckpt}", f"device={device}", f"num_workers={num_workers}",
                                     f"progress={str(progress).lower()}", *overrides])


def refuse_out_that_is_no_folder(out: Path, names: list[str], command: str) -> None:
    """out= is the folder the tables (`names`) go in: where it, or a folder above it, is an existing file, refused
    before anything is evaluated. overwrite=true replaces the tables in a folder, never another file."""
    for path in (out, *out.parents):
        if path.is_dir():
            return
        if path.exists():
            raise ConfigError(f"out={out}: {path} is a file, not a folder; {command} writes {' and '.join(names)} "
                              "into the folder out= names (overwrite=true replaces those tables, never another "
                              "file). Choose another out=")


def refuse_taken(targets: list[Path], overwrite: bool) -> None:
    """Existing tables are refused unless `overwrite`, before anything is evaluated."""
    taken = [str(p) for p in targets if p.exists()]
    if taken and not overwrite:
        raise ConfigError(f"{' and '.join(taken)} already exist; choose another out=, or overwrite=true")


def write_whole(path: Path, text: str, overwrite: bool) -> None:
    """`text` into `path` through a temp file beside it: whole or not at all; an existing file is kept unless
    `overwrite`, even one that appeared while the table was computed."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise ConfigError(f"{path} appeared while the table was computed; it is kept. Run again with "
                                  f"another out=, or overwrite=true. The table:\n{text}") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
