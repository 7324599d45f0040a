"""A cross-view run's config, parsed once at the door into typed objects that the rest of the run is handed.

    run = parse_training(cfg)      # train.py: every section checked, nothing read or built yet
    run = parse_evaluation(cfg, stored)   # evaluate.py: the checkpoint's config, with the test condition asked for

Every check that can fail on the config alone runs here, before any data is read, generated or decoded: the
dataset's shared keys (CrossViewDataConfig) and its reader's own keys, the model section, the trainer section (its
monitored metric among the keys validation can report: validation_keys.py) and the name and arguments of every
registered component (backbone, head, loss, optimizer, sampler, query views).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from omegaconf import DictConfig, OmegaConf

import geoloc.tasks.crossview.view_pairs  # noqa: F401  (declares the query_views kind, registers its built-ins)
from geoloc import registry
from geoloc.config import ConfigError, EvaluateKeys, TrainKeys, checked, defaults_of, to_yaml, top_level
from geoloc.engine import TrainerConfig
from geoloc.models.crossview import CrossViewModelConfig
from geoloc.tasks.crossview.data_config import CrossViewDataConfig, parse_dataset
from geoloc.gallery.index_settings import GalleryConfig
from geoloc.tasks.crossview.refine import RefineConfig, parse_refiner, refine_nodes
from geoloc.tasks.crossview.validation_keys import check_monitor, validation_plan

#: the registered kinds a cross-view network and its training are built from (registry.section: their sections)
COMPONENTS = ("backbone", "head", "loss", "optimizer", "sampler", "query_views")
#: what a resume may change besides the engine's keys (geoloc/launch/resume.py): the processes that render the
#: synthetic set, which write the same files either way, and whether decoded images are kept (the same items)
RESUME_MAY_CHANGE = ("dataset.workers", "dataset.cache_decoded")
# transform settings that must match what the network was trained on: evaluation always takes them from the
# checkpoint. The field of view and heading are the test condition, which evaluate.py may set.
TRANSFORM_KEYS = ("alignment", "aerial_size", "pano_size", "ground_extent_m", "camera_height_m")
# what an evaluation may take from the command line besides the reader's own keys: which data (the dataset and its
# root, split and checks) and the test condition (field of view, heading). Batch sizes and augmentation stay as
# trained: they do not change what is measured.
EVALUATION_KEYS = ("name", "module", "root", "split", "check_files", "max_val", "fov", "random_heading",
                   "heading_steps")


def config_nodes() -> dict[str, dict]:
    """The defaults geoloc/conf/ extends (geoloc/launch/schemas.py), from their one home: `backbone/vgg16` ... for every
    registered component (its factory's signature), `dataset/<reader>` for every reader (the shared keys, then the
    reader's own), `model` and `gallery` (their dataclasses)."""
    nodes = {f"{registry.section(kind)}/{name}": registry.with_defaults(kind, {"name": name})
             for kind in COMPONENTS for name in registry.names(kind)}
    shared = defaults_of(CrossViewDataConfig)
    nodes.update({f"dataset/{name}": {**shared, **registry.with_defaults("dataset", {"name": name})}
                  for name in registry.names("dataset")})
    nodes.update(refine_nodes())
    return {**nodes, "model": defaults_of(CrossViewModelConfig), "gallery": defaults_of(GalleryConfig)}


@dataclass(frozen=True)
class Components:
    """The registered parts of the network and its training, each a config section {name, module, **keys}."""

    backbone: dict
    head: dict
    loss: dict
    optim: dict
    sampler: dict = field(default_factory=lambda: {"name": "shuffle"})
    views: dict = field(default_factory=lambda: {"name": "single"})  # the query views of a training pair
    refiner: dict | None = None  # the refiner's own keys (refine.py), or None: retrieval alone
    refine: RefineConfig | None = None  # how the refiner trains and is tested

    def section(self, kind: str) -> dict:
        return getattr(self, registry.section(kind))


@dataclass(frozen=True)
class CrossViewTraining:
    """Everything a training run reads from its config."""

    data: CrossViewDataConfig
    reader: dict  # the dataset section's reader keys: name, module and the reader's own arguments
    model: CrossViewModelConfig
    components: Components
    trainer: TrainerConfig
    job: TrainKeys  # seed, ckpt, init_from, figures
    yaml: str = ""  # the resolved config, as checkpoints store it

    @property
    def monitor(self) -> str:
        """The validation metric that selects best.pt: trainer.monitor, else the task's own (the trainer's rule)."""
        from geoloc.tasks.crossview.task import CrossViewTask

        return self.trainer.monitor or CrossViewTask.monitor

    @property
    def refine(self) -> RefineConfig | None:
        """How the refiner trains and is tested; None for retrieval alone (no refiner section)."""
        return self.components.refine if self.components.refiner else None


@dataclass(frozen=True)
class CrossViewEvaluation:
    """Everything an evaluation reads: the checkpoint's network and transforms, the split and test condition asked
    for, and where the numbers go."""

    data: CrossViewDataConfig
    reader: dict
    model: CrossViewModelConfig
    components: Components
    job: EvaluateKeys  # ckpt, metrics_out, device, num_workers, progress
    gallery: GalleryConfig
    run_dir: str | None = None
    precision: str = "32"  # the run's trainer.precision: its autocast on CUDA, as in training's validation
    cpu_precision: str = "32"  # the run's trainer.cpu_precision: its autocast on the CPU

    @property
    def batch_size(self) -> int:
        return self.data.val_batch_size or self.data.batch_size


def _plain(section) -> dict:
    """A config section as a dict; a mandatory value left unset (`???`) reads as absent."""
    if section is None:
        return {}
    if isinstance(section, DictConfig):
        return {k: v for k, v in OmegaConf.to_container(section, resolve=True).items() if v != "???"}
    return dict(section)


def parse_components(cfg: DictConfig) -> Components:
    """The component sections of `cfg`, each checked against its registered factory (name and arguments)."""
    sections = {registry.section(kind): _plain(cfg.get(registry.section(kind))) for kind in COMPONENTS}
    if not sections["sampler"]:  # checkpoints written before samplers were a group
        sections["sampler"] = {"name": "shuffle"}
    if not sections["views"]:  # a run that names no query views (the default, and checkpoints before the kind)
        sections["views"] = {"name": "single"}
    for kind in COMPONENTS:
        section = registry.section(kind)
        if not sections[section]:
            raise ConfigError(f"config section '{section}' is missing; choose one with {section}=<option>")
        registry.check(kind, sections[section])
    refine, refiner = parse_refiner(_plain(cfg.get("refiner")))
    return Components(**sections, refiner=refiner, refine=refine)


def parse_training(cfg: DictConfig) -> CrossViewTraining:
    """train.py's config, checked section by section (module docstring)."""
    data, reader = parse_dataset(cfg.dataset)
    trainer = checked(cfg.trainer, TrainerConfig, "trainer")
    model = checked(cfg.model, CrossViewModelConfig, "model")
    components = parse_components(cfg)
    run = CrossViewTraining(data=data, reader=reader, model=model, components=components, trainer=trainer,
                            job=top_level(cfg, TrainKeys, "train.py"), yaml=to_yaml(cfg))
    check_monitor(run.monitor, validation_plan(data, run.refine), "under this config")
    return run


def parse_evaluation(cfg: DictConfig, stored: DictConfig) -> CrossViewEvaluation:
    """evaluate.py's config: the checkpoint's `stored` config, with the dataset and test condition asked for in
    `cfg` (EVALUATION_KEYS and another reader's own keys; TRANSFORM_KEYS always as trained)."""
    data, reader = parse_dataset(evaluated_dataset(stored.dataset, cfg.get("dataset")))
    model = checked(stored.model, CrossViewModelConfig, "model")
    components = parse_components(stored)
    gallery = checked(cfg.get("gallery") or {}, GalleryConfig, "gallery")
    return CrossViewEvaluation(data=data, reader=reader, model=model, components=components,
                               job=top_level(cfg, EvaluateKeys, "evaluate.py"), gallery=gallery,
                               run_dir=OmegaConf.select(cfg, "run_dir", throw_on_resolution_failure=False),
                               **stored_precision(stored))


def stored_precision(stored: DictConfig) -> dict[str, str]:
    """The autocast a run trained and validated under, from its stored config: {"precision": trainer.precision (on
    CUDA), "cpu_precision": trainer.cpu_precision (on the CPU)}, "32" where the config has none; evaluate.py and
    the apps compute under the same."""
    return {key: str(OmegaConf.select(stored, f"trainer.{key}", default="32")) for key in ("precision", "cpu_precision")}


def evaluated_dataset(stored: DictConfig | dict, requested: DictConfig | dict | None) -> dict:
    """The dataset section an evaluation reads: the stored one, overlaid with what was asked for.

    Another dataset (a different `name`) keeps only the stored shared keys, so its reader's own keys come from the
    request or the reader's defaults, and never inherits the trained one's root."""
    section = _plain(stored)
    overlay = {k: v for k, v in _plain(requested).items() if v is not None}
    if overlay.get("name") not in (None, section.get("name")):
        section = {k: v for k, v in section.items() if k in CrossViewDataConfig.__dataclass_fields__
                   and k != "module"}
        section["root"] = None
    shared = CrossViewDataConfig.__dataclass_fields__
    for key, value in overlay.items():
        if key in TRANSFORM_KEYS:
            continue
        if key in EVALUATION_KEYS or key not in shared:
            section[key] = value
    return section


def canonical_config(cfg: DictConfig) -> dict:
    """A training config as a resume compares it (geoloc/launch/resume.py): parsed, with every default filled in,
    the reader's and each component's signature defaults included, so only what would compute differently
    differs. Configs of older layouts are upgraded first (legacy.py)."""
    from geoloc.tasks.crossview.legacy import is_old_layout, upgraded_config

    run = parse_training(upgraded_config(cfg) if is_old_layout(cfg) else cfg)
    return {
        "dataset": {**asdict(run.data), **registry.with_defaults("dataset", run.reader)},
        "model": asdict(run.model),
        **{registry.section(kind): registry.with_defaults(kind, run.components.section(kind)) for kind in COMPONENTS},
        "trainer": asdict(run.trainer),
        **asdict(run.job),
        **({"refiner": {**asdict(run.components.refine), **registry.with_defaults("refiner", run.components.refiner)}}
           if run.components.refiner else {}),
    }
