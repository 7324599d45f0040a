"""FAISS on one OpenMP thread for a test module: a parallel HNSW build is not reproducible, and OpenMP on a busy
shared CPU is slow. `from helpers.faiss_threads import one_faiss_thread  # noqa: F401` makes it autouse."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def one_faiss_thread():
    faiss = pytest.importorskip("faiss")
    before = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    yield
    faiss.omp_set_num_threads(before)
