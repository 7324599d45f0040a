"""The evaluation rules of the field's reference code, gmberton/VPR-methods-evaluation, rewritten (not copied) as
brute-force loops, for tests to hold geoloc's own-data reader and scorer against."""

from __future__ import annotations

import numpy as np


def reference_east_north(path: str) -> tuple[float, float]:
    """test_dataset.py's reading of a path `path/to/file/@utm_east@utm_north@...@.jpg`: the path is split at '@',
    field 1 is the UTM east and field 2 the UTM north, as floats; nothing else of the path is read."""
    fields = path.split("@")
    return float(fields[1]), float(fields[2])


def reference_positives(query_east_north, tile_east_north, radius_m: float = 25.0) -> list[set[int]]:
    """test_dataset.py's positives: the database images within `radius_m` metres of the query in UTM metres, those
    at exactly the radius included (a radius search, as scikit-learn's radius_neighbors), and nothing else."""
    return [{j for j, t in enumerate(tile_east_north) if np.hypot(*(np.asarray(q) - t)) <= radius_m}
            for q in query_east_north]


def reference_recalls(query, reference, positives, ks) -> dict[str, float]:
    """main.py's recall: each query's predictions are the references by descending inner product; a query is found
    at K when one of its first K predictions is a positive, and the share is over every query, those without a
    positive included."""
    predictions = np.argsort(-(query @ reference.T), axis=1)
    return {f"R@{k}": float(np.mean([bool(set(p[:k].tolist()) & pos) for p, pos in zip(predictions, positives)]))
            for k in ks}
