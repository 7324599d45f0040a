"""benchmarks/bench_overhead.py times geoloc's recall against a bare matmul with a count: the two must compute the
same numbers, or the ratio compares different work."""

import importlib.util

import torch
from conftest import REPO

from geoloc.eval.retrieval_metrics import retrieval_metrics


def load(name):
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_bare_recall_is_geolocs_recall():
    bench, data = load("bench_overhead"), load("synthetic_descriptors")
    query, reference = (torch.from_numpy(a) for a in data.make_data(2500, 2500, 32, noise=0.3, seed=1, rank=8))
    bare = bench.bare_recall(query, reference, (1, 5, 10, 25))  # 2,500 queries: three chunks of 1,024
    ours = retrieval_metrics(query, reference)
    assert 0.05 < ours["R@1"] < 0.95  # a ranking with misses, so a wrong count shows
    assert [bare[f"R@{k}"] for k in (1, 5, 10, 25)] == [ours[k] for k in ("R@1", "R@5", "R@10", "R@1%")]
