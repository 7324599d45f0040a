"""A dataset plug-in: a folder of `<split>/street/<id>.png` panoramas and `<split>/aerial/<id>.png` tiles."""

from pathlib import Path

import numpy as np
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.registry import register


@register("dataset", "tiny_folder")
def tiny_folder(root: str, split: str, extension: str = ".png") -> RetrievalSplit:
    streets = sorted((Path(root) / split / "street").glob(f"*{extension}"))
    aerials = [Path(root) / split / "aerial" / p.name for p in streets]
    return RetrievalSplit(name=f"tiny_folder/{split}", root=root, queries=streets, references=aerials,
                          positives=np.arange(len(streets)))
