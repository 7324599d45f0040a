"""benchmarks/bench_eval.py makes float32 data (benchmarks/synthetic_descriptors.py): the exact torch search keeps
its input dtype, so float64 data would time exact search on twice the bytes and hold twice the memory against the
float32 FAISS indexes."""

import importlib.util
from conftest import REPO

import numpy as np

BENCH = REPO / "benchmarks" / "synthetic_descriptors.py"


def test_make_data_gives_float32_unit_rows():
    spec = importlib.util.spec_from_file_location("synthetic_descriptors", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    query, reference = bench.make_data(300, 20, 48, noise=1.0, seed=0, rank=8)
    assert query.dtype == np.float32 and reference.dtype == np.float32
    assert query.shape == (20, 48) and reference.shape == (300, 48)
    np.testing.assert_allclose(np.linalg.norm(reference, axis=1), 1, atol=1e-5)
