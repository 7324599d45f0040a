"""Cross-view geo-localization: street (or drone) queries against aerial references. See docs/architecture.md.

`train(cfg, run_dir)` trains and validates; `evaluate(cfg, state)` scores a checkpoint's state on a split.
"""

from geoloc.tasks.crossview.run import evaluate, train

__all__ = ["evaluate", "train"]
