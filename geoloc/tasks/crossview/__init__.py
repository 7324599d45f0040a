"""Cross-view geo-localization: street (or drone) queries against aerial references. See docs/architecture.md.

`train(cfg, run_dir)` trains and validates; `evaluate(cfg, state)` scores a checkpoint's state on a split;
`build_run(cfg, run_dir)` gives what train.py builds before its first epoch (task, trainer, data: a `Run`), for
benchmarks and tools.
RESUME_MAY_CHANGE and canonical_config say how a resume compares configs (geoloc/launch/resume.py). The apps
(localize.py, `geoloc serve`, export.py) use what this package exports and nothing deeper: `CrossViewEncoder` (a
checkpoint's network, preprocessing and input spec), `LocalizationResult` (one query's answer) and a saved gallery,
checked and bound to the weights that built it (`open_gallery` -> `SavedGallery`: the index and its places,
`Places`, `POSITION_KEYS`), and `merge_shards` (one gallery from shard jobs' folders: `geoloc gallery merge`).
`config_nodes()` gives the defaults geoloc/conf/ extends. The package registers itself as the task `crossview`.
"""

import sys

from geoloc import registry
from geoloc.tasks.crossview.crossview_config import RESUME_MAY_CHANGE, canonical_config, config_nodes
from geoloc.tasks.crossview.encoder import CrossViewEncoder
from geoloc.gallery.confidence import TOP1, WITHIN_5M, calibrators, refine_features, refiner_calibrator
from geoloc.gallery.folder import SavedGallery, open_gallery
from geoloc.gallery.shards import merge_shards
from geoloc.gallery.answer import LocalizationResult
from geoloc.gallery.places import POSITION_KEYS, Places, read_places
from geoloc.tasks.crossview.crossview_run import Run, build_run, evaluate, sweep_metric, train

registry.register("task", "crossview", sys.modules[__name__])
# the modules' names before 2026-11-28, kept for one release: .config is crossview_config, .run is crossview_run
sys.modules[f"{__name__}.config"] = sys.modules[f"{__name__}.crossview_config"]
sys.modules[f"{__name__}.run"] = sys.modules[f"{__name__}.crossview_run"]

__all__ = ["CrossViewEncoder", "LocalizationResult", "POSITION_KEYS", "Places", "RESUME_MAY_CHANGE", "Run",
           "SavedGallery", "TOP1", "WITHIN_5M", "build_run", "calibrators", "canonical_config", "config_nodes", "evaluate", "merge_shards",
           "open_gallery", "read_places", "refine_features", "refiner_calibrator", "sweep_metric", "train"]
