"""Cross-view geo-localization: street (or drone) queries against aerial references. See docs/architecture.md.

`train(cfg, run_dir)` trains and validates; `evaluate(cfg, state)` scores a checkpoint's state on a split.
RESUME_MAY_CHANGE and canonical_config say how a resume compares configs (geoloc/launch/resume.py).
"""

from geoloc.tasks.crossview.config import RESUME_MAY_CHANGE, canonical_config
from geoloc.tasks.crossview.run import evaluate, train

__all__ = ["RESUME_MAY_CHANGE", "canonical_config", "evaluate", "train"]
