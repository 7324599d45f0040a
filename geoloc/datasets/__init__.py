"""The registered cross-view datasets. A dataset is a reader: `reader(root, split, **config keys) -> RetrievalSplit`
(paths and which references are relevant to which query; nothing decoded). This package declares the `dataset`
kind, and importing it registers the built-in readers: cvusa and synthetic (cvusa.py), cvact, vigor, u1652 and
folder (your own street images and aerial tiles with their positions). The cross-view data module (geoloc/tasks/crossview/datasets.py) turns a split into training pairs and evaluation sets.

root=None reads the embedded synthetic data, rendered on first use into $GEOLOC_CACHE (docs/synthetic.md).
"""

from geoloc import registry
from geoloc.datasets import cvact, cvusa, folder, u1652, vigor  # noqa: F401  (each registers its reader)

registry.declare("dataset", section="dataset", runtime=("root", "split"))
