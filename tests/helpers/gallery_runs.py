"""evaluate.py's gallery path on given descriptors: no network, no images, milliseconds."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.tasks.crossview import gallery_build as crossview_gallery
from geoloc.tasks.crossview.datasets import EvalData
from geoloc.gallery.index_settings import GalleryConfig

# what run.score records of the weights and the reader that built a gallery
META = {"ckpt": "/runs/a/best.pt", "model_fingerprint": "a" * 64, "dataset": "pairs"}


def pairs_split(n, root="/data", name="pairs"):
    """A one-to-one RetrievalSplit of n pairs (query i matches reference i)."""
    return RetrievalSplit(name, root, [f"q{i}.jpg" for i in range(n)], [f"r{i}.jpg" for i in range(n)],
                          np.arange(n))


def gallery_evaluate(monkeypatch, split, query, reference, meta=META, **cfg):
    """crossview_gallery.evaluate of `split` with encode_split() replaced by the given descriptors (`rows`: those
    references)."""
    def encode_split(task, engine, data, batch_size, sides=("query", "reference"), rows=None, refine=False):
        assert not refine  # a task without a refiner asks for no refiner maps
        given = {"query": query, "reference": reference if rows is None else reference[list(rows)]}
        return {k: given[k] for k in sides}

    monkeypatch.setattr(crossview_gallery, "encode_split", encode_split)
    task = SimpleNamespace(model_cfg=SimpleNamespace(dim=query.shape[1]), refiner=None)  # retrieval alone
    engine = SimpleNamespace(device=torch.device("cpu"))
    return crossview_gallery.evaluate(task, engine, EvalData(split), 4, GalleryConfig(**cfg), meta)
