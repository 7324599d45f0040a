"""Synthetic unit descriptors for the retrieval benchmarks (bench_eval.py, bench_overhead.py): a low intrinsic
dimension, as learned descriptors have (isotropic random vectors would leave an IVF nothing to cluster), made from a
seed; the largest galleries as a stream of blocks, each made again from (seed, block start) alone."""
import numpy as np


def make_data(n_ref, n_query, dim, noise, seed, rank=64, iso=0.1):
    """Unit descriptors with a low intrinsic dimension, as learned ones have (isotropic random vectors would
    leave IVF nothing to cluster): reference = z W + a little isotropic noise, z ~ N(0, I_rank); query i is
    z_i + noise * N(0, I_rank) mapped by the same W."""
    rng = np.random.default_rng(seed)
    # float32 throughout (numpy >= 2 would promote to float64 on a np.sqrt scalar): the exact torch search keeps
    # the dtype it is given, and float64 would time it on twice the bytes.
    w = rng.standard_normal((rank, dim), dtype=np.float32) / np.float32(np.sqrt(rank))
    z = rng.standard_normal((n_ref, rank), dtype=np.float32)
    ref = z @ w
    scale = np.float32(iso / np.sqrt(dim)) * np.linalg.norm(ref, axis=1, keepdims=True)
    for s in range(0, n_ref, 100_000):  # in blocks: no second n_ref x dim temporary
        ref[s:s + 100_000] += scale[s:s + 100_000] * rng.standard_normal((min(100_000, n_ref - s), dim),
                                                                          dtype=np.float32)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    query = (z[:n_query] + noise * rng.standard_normal((n_query, rank), dtype=np.float32)) @ w
    query /= np.linalg.norm(query, axis=1, keepdims=True)
    return query, ref


def latent_map(dim, seed, rank=64):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((rank, dim), dtype=np.float32) / np.float32(np.sqrt(rank))


def stream_block(w, start, stop, seed, iso=0.1):
    """References start..stop of a stream of make_data's kind, made from (seed, block start) alone: any block can
    be made again without the others. Returns (latent codes, unit references)."""
    rng = np.random.default_rng([seed, start])
    z = rng.standard_normal((stop - start, w.shape[0]), dtype=np.float32)
    ref = z @ w
    scale = np.float32(iso / np.sqrt(w.shape[1])) * np.linalg.norm(ref, axis=1, keepdims=True)
    ref += scale * rng.standard_normal(ref.shape, dtype=np.float32)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    return z, ref
