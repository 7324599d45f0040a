"""What the readers share: a one-to-one split from pairs, and their start-up refusals."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from geoloc.config import ConfigError
from geoloc.data.retrieval_split import RetrievalSplit


def pairs_split(name: str, root, pairs: list[tuple[Path, Path]], query_view: str = "panorama",
                positions: tuple[str, np.ndarray] | None = None) -> RetrievalSplit:
    """A one-to-one split from (street, aerial) pairs: query i matches reference i. positions: (kind, P x 2),
    kind "xy" (metres) or "latlon" (degrees), where pair i was taken; its query and reference share it."""
    where = {}
    if positions is not None:
        kind, array = positions
        where = {f"query_{kind}": array, f"reference_{kind}": array}
    return RetrievalSplit(name=name, root=Path(root), queries=[street for street, _ in pairs],
                          references=[aerial for _, aerial in pairs], positives=np.arange(len(pairs)),
                          query_view=query_view, **where)


def with_view(split: RetrievalSplit, view: str) -> RetrievalSplit:
    return replace(split, query_view=view)


def require_root(root, name: str) -> None:
    if not root:
        raise ConfigError(f"dataset={name} needs dataset.root=/path/to/{name.upper()} (it is missing); the embedded "
                          "synthetic data is dataset=synthetic, vigor or u1652 with no root")
