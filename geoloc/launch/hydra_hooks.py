"""Hydra glue that acts before Hydra composes a config or writes into a run dir.

- the schema nodes (geoloc/launch/schemas.py), stored when this module is imported (train.py, evaluate.py,
  localize.py, export.py, and tests that compose configs): every config key's default, from its one home;
- `${out_or:DEFAULT}` (geoloc/conf/localize.yaml's run dir): `out=` when given, else DEFAULT;
- `${pid:}`, registered when this module is imported (train.py, evaluate.py): the process id, so default run dirs
  `outputs/<task>/<dataset>/<date>_<time>_<pid>` differ even for runs started in the same second. Cached like
  Hydra's `${now:}`, so a sweep job started by a launcher in another process resolves the sweep dir to the same
  folder (Hydra copies the resolver cache into each job's config; the job process imports this module when it
  unpickles the callback below, which registers the resolver there too).
- `compose_conf`: a config composed in-process (apps, tools, benchmarks, tests) exactly as the entry point of the
  same name composes it, these registrations included; `compose_checked`: into an app's dataclass, checked once;
- `hydra_overrides_for_rank`: ranks > 0 of a torchrun / srun launch of train.py write into a throwaway Hydra
  dir, so one launch makes one run dir.
- `RefuseTakenRunDir`: Hydra writes `.hydra/` into the run dir before the app starts, so a run refused only by
  the app (geoloc/launch/rundir.py) would already have overwritten the config record of the run it protects.
  This callback refuses a taken `hydra.run.dir` first. (Under `-m`, Hydra writes each job's `.hydra/` before any
  hook can see the job's folder; there the app's refusal is the only one.)
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.errors import HydraException
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from geoloc.config import ConfigError, T, checked
from geoloc.launch import schemas

CONF = Path(__file__).resolve().parents[1] / "conf"


def register_resolvers() -> None:
    OmegaConf.register_new_resolver("pid", lambda: os.getpid(), replace=True, use_cache=True)
    OmegaConf.register_new_resolver("out_or", out_or, replace=True)


def out_or(default: str, *, _root_: DictConfig) -> str:
    """`${out_or:DEFAULT}`: the config's `out` when the command line gave one, else DEFAULT. localize.py's run dir
    is its out= folder, so out=DIR makes no second, empty folder under outputs/localize/."""
    node = _root_._get_node("out")
    if node is None or node._is_interpolation() or node._is_missing() or node._value() is None:
        return default
    return str(node._value())


def compose_conf(name: str, overrides: list[str], conf: str | Path = CONF) -> DictConfig:
    """`geoloc/conf/<name>.yaml` with `overrides`, as `python <name>.py <overrides>` composes it; `conf`: another
    folder of configs (a benchmark comparing checkouts)."""
    if not (Path(conf) / f"{name}.yaml").is_file():
        raise ConfigError(f"{conf} holds no {name}.yaml: pass a folder of geoloc configs (geoloc/conf/ of a checkout "
                          "or of the installed package)")
    with initialize_config_dir(str(Path(conf).resolve()), version_base="1.3"):
        return compose(name, overrides=list(overrides))


def compose_checked(name: str, schema: type[T], overrides: list[str], where: str) -> T:
    """`geoloc/conf/<name>.yaml` (extending dataclass `schema`'s defaults, stored as `schema/<name>`) with `overrides`
    in Hydra's grammar, as the entry points take theirs, checked once into `schema`; ConfigError names `where`."""
    schemas.store_dataclass(name, schema)
    try:
        return checked(compose_conf(name, overrides), schema, where)
    except HydraException as err:  # Hydra's lines less its pointers: the schema holds every key, none to append (+)
        said = " ".join(line for line in str(err).splitlines() if not line.startswith(("See https://", "To append")))
        raise ConfigError(f"bad '{where}' config: {said}") from None


class RefuseTakenRunDir(Callback):
    """`role`: "training" (train.py: a folder with outputs only to resume it), "evaluation" or "localization"
    (never a training's folder)."""

    def __init__(self, role: str = "training"):
        self.role = role

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        from geoloc.engine.distributed import launch_rank
        from geoloc.launch.rundir import RunDirTaken, refuse_if_taken

        if launch_rank() > 0:  # ranks > 0 run in a throwaway Hydra dir and write nothing
            return
        try:
            refuse_if_taken(config.hydra.run.dir, ckpt=config.get("ckpt"), role=self.role)
        except RunDirTaken as err:
            # Hydra turns a callback's exception into a warning and goes on; SystemExit stops it (exit status 1)
            raise SystemExit(f"RunDirTaken: {err}") from None


def hydra_overrides_for_rank() -> list[str]:
    """Hydra overrides for ranks > 0 of a torchrun / srun launch of train.py.

    Each rank runs Hydra itself, and `${now:...}` in the run dir can differ by a second between ranks, which
    would make a second run dir. Ranks > 0 get a throwaway Hydra dir without logs or .hydra/ (they write
    nothing: rank 0 owns the run dir), so there is one run dir per launch.
    """
    from geoloc.engine.distributed import launch_rank

    rank_ = launch_rank()
    if rank_ == 0:
        return []
    scratch = os.path.join(tempfile.gettempdir(), f"geoloc-hydra-rank{rank_}")
    return [f"hydra.run.dir={scratch}", "hydra.output_subdir=null", "hydra/job_logging=disabled",
            "hydra/hydra_logging=disabled"]


register_resolvers()
schemas.register()
