"""MMDIP: place recognition in dynamic scenes ("Multi-modal Visual Place Recognition in Dynamics-Invariant
Perception Space", Wu, Wang, Sun), as a task on the geoloc engine. See docs/mmdip.md.

`train(cfg, run_dir)` runs phase 1 -> phase 2 -> VPR evaluation; `evaluate(cfg, state)` scores the
checkpoint cfg.ckpt (recall on `dataset=dynamic`, L1/L2/PSNR/SSIM on `dataset=emptycities`); `config_nodes()`
gives the defaults geoloc/conf/ extends. The package registers itself as the task `mmdip`; its modules declare the kinds
only it builds: `segmenter` (networks.py), `generator_loss` (generator_loss.py) and `mmdip_dataset` (readers.py).
"""

import sys

from geoloc import registry
from geoloc.tasks.mmdip.config_nodes import config_nodes
from geoloc.tasks.mmdip.pipeline import evaluate, sweep_metric, train

registry.register("task", "mmdip", sys.modules[__name__])

__all__ = ["config_nodes", "evaluate", "sweep_metric", "train"]
