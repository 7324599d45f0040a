"""Cross-view geo-localization: street (or drone) queries against aerial references. See docs/architecture.md.

`train(cfg, run_dir)` trains and validates; `evaluate(cfg, state)` scores a checkpoint's state on a split. The
package registers itself as the task `crossview`.
"""

import sys

from geoloc import registry
from geoloc.tasks.crossview.run import evaluate, train

registry.register("task", "crossview", sys.modules[__name__])

__all__ = ["evaluate", "train"]
