"""Retrieval evaluation: time and peak memory of recall / gallery search, exact against FAISS IVF-PQ.

Two settings, each case in its own process so that its peak memory is its own:
1. CVUSA val size: N = 8,884 queries and references, D = 4,096 (the paper's descriptor size): recall_at_k with
   the exact torch backend and with the FAISS flat backend (the two must print the same recall).
2. A country-scale gallery: 1,000,000 references. 1M x 4,096 float32 is 16 GB, more than a shared 24 GB machine
   should hold, so the default is D = 512 (2 GB); pass --large-dim 4096 on a machine that has the memory.
   Exact search (torch, chunked) against IVF-PQ (FAISS): build time, query time, peak memory and the recall
   IVF-PQ keeps. Only --large-queries queries are timed (default 1,000); the gallery is full size.

Data: synthetic unit descriptors of intrinsic dimension --rank (64) in D dimensions, plus a little isotropic noise;
query i is reference i's latent code plus --noise (--large-noise) Gaussian noise, chosen so that exact recall is
high but not 100%. Peak memory is the rise of the process's peak RSS (VmHWM) over the RSS after the data was made.

    OMP_NUM_THREADS=1 python benchmarks/bench_eval.py                   # both settings, ~5 min on one idle core
    python benchmarks/bench_eval.py --large-n 0                         # CVUSA size only
    python benchmarks/bench_eval.py --large-n 200000 --large-queries 500  # quicker large setting
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np


def make_data(n_ref, n_query, dim, noise, seed, rank=64, iso=0.1):
    """Unit descriptors with a low intrinsic dimension, as learned ones have (isotropic random vectors would
    leave IVF nothing to cluster): reference = z W + a little isotropic noise, z ~ N(0, I_rank); query i is
    z_i + noise * N(0, I_rank) mapped by the same W."""
    rng = np.random.default_rng(seed)
    w = rng.standard_normal((rank, dim), dtype=np.float32) / np.sqrt(rank)
    z = rng.standard_normal((n_ref, rank), dtype=np.float32)
    ref = z @ w
    scale = iso * np.linalg.norm(ref, axis=1, keepdims=True) / np.sqrt(dim)
    for s in range(0, n_ref, 100_000):  # in blocks: no second n_ref x dim temporary
        ref[s:s + 100_000] += scale[s:s + 100_000] * rng.standard_normal((min(100_000, n_ref - s), dim),
                                                                          dtype=np.float32)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    query = (z[:n_query] + noise * rng.standard_normal((n_query, rank), dtype=np.float32)) @ w
    query /= np.linalg.norm(query, axis=1, keepdims=True)
    return query, ref


def _status(field):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024  # kB -> MiB
    return float("nan")


def reset_peak():
    """Reset VmHWM to the current RSS (Linux >= 4.0); returns False where that is not allowed."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def run_case(args):
    """Child process: one case; prints one JSON line."""
    import torch

    torch.set_num_threads(args.threads)
    from geoloc.eval import GalleryIndex, recall_at_k

    small = args.case.startswith("small")
    n_ref = args.n if small else args.large_n
    n_query = args.n if small else args.large_queries
    dim = args.dim if small else args.large_dim
    query, ref = make_data(n_ref, n_query, dim, args.noise if small else args.large_noise, args.seed,
                             rank=args.rank)
    base = _status("VmRSS")
    exact_peak = reset_peak()
    res = {"case": args.case, "n_ref": n_ref, "n_query": n_query, "dim": dim}

    if args.case == "small-torch":
        res["recall"], res["time_s"] = timed(lambda: recall_at_k(query, ref, backend="torch"))
    elif args.case == "small-faiss":
        import faiss

        faiss.omp_set_num_threads(args.threads)
        res["recall"], res["time_s"] = timed(lambda: recall_at_k(query, ref, backend="faiss"))
    elif args.case == "large-exact":
        index = GalleryIndex(dim, backend="torch").add(ref)
        (_, idx), res["time_s"] = timed(lambda: index.search(query, 10))
        res["recall"] = recall_from_topk(idx.numpy())
    elif args.case == "large-ivfpq":
        import faiss

        faiss.omp_set_num_threads(args.threads)
        index = GalleryIndex(dim, backend="faiss", kind="ivfpq", nlist=args.nlist, m=args.m, nbits=args.nbits)
        _, res["build_s"] = timed(lambda: (index.train(ref, max_points=args.train_points), index.add(ref)))
        res["index_mib"] = (index._index.code_size + 8) * n_ref / 2**20  # PQ codes + 64-bit ids
        res["probes"] = []
        for nprobe in args.nprobe:
            index.set_nprobe(nprobe)
            (_, idx), time_s = timed(lambda: index.search(query, 10))
            res["probes"].append(dict(nprobe=nprobe, time_s=time_s, recall=recall_from_topk(idx.numpy())))
    res["peak_mib"] = _status("VmHWM") - base
    res["peak_is_exact"] = exact_peak
    print(json.dumps(res))


def recall_from_topk(idx):
    hit_rank = np.where(idx == np.arange(idx.shape[0])[:, None], np.arange(idx.shape[1]), idx.shape[1]).min(1)
    return {f"R@{k}": float(np.mean(hit_rank < k)) for k in (1, 5, 10)}


def spawn(case, argv):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [ROOT, os.environ.get("PYTHONPATH")])))
    out = subprocess.run([sys.executable, __file__, "--case", case, *argv], capture_output=True, text=True,
                         env=env)
    if out.returncode != 0:
        raise RuntimeError(f"case {case} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def fmt_recall(r):
    return " ".join(f"{k} {100 * v:6.2f}" for k, v in r.items())


def main(args, argv):
    sys.stdout.reconfigure(line_buffering=True)  # figures appear as each case ends
    results = []
    print(f"machine: {os.cpu_count()} CPUs, threads {args.threads}; data: synthetic descriptors of intrinsic "
          f"dimension {args.rank}, query noise {args.noise} (CVUSA size) / {args.large_noise} (large)")
    if args.n:
        print(f"\n[1] CVUSA size: N = {args.n:,} queries and references, D = {args.dim:,}")
        for case in ("small-torch", "small-faiss"):
            r = spawn(case, argv)
            results.append(r)
            print(f"  {case:12s} {r['time_s']:7.2f} s   peak +{r['peak_mib']:7.0f} MiB   {fmt_recall(r['recall'])}")
    if args.large_n:
        print(f"\n[2] large gallery: {args.large_n:,} references, D = {args.large_dim} ({args.large_n:,} x 4,096 "
              f"float32 would take {args.large_n * 4096 * 4 / 2**30:.1f} GiB), {args.large_queries:,} queries, top-10")
        exact, ivf = spawn("large-exact", argv), spawn("large-ivfpq", argv)
        results += [exact, ivf]
        per_query = 1e3 / args.large_queries
        print(f"  exact (torch)  search {exact['time_s']:7.2f} s ({per_query * exact['time_s']:6.2f} ms/query)   "
              f"peak +{exact['peak_mib']:6.0f} MiB   {fmt_recall(exact['recall'])}")
        print(f"  IVF-PQ nlist {args.nlist} m {args.m} nbits {args.nbits}, trained on "
              f"{min(args.train_points, args.large_n):,}: build {ivf['build_s']:.1f} s, codes {ivf['index_mib']:.0f} "
              f"MiB, peak +{ivf['peak_mib']:.0f} MiB")
        for p in ivf["probes"]:
            kept = ", ".join(f"{100 * p['recall'][k] / v:.1f}% of {k}" for k, v in exact["recall"].items() if v)
            print(f"    nprobe {p['nprobe']:4d}  search {p['time_s']:7.2f} s ({per_query * p['time_s']:6.2f} "
                  f"ms/query, {exact['time_s'] / p['time_s']:5.1f}x faster)   {fmt_recall(p['recall'])}   "
                  f"keeps {kept}")
    if not all(r["peak_is_exact"] for r in results):
        print("  (peak RSS could not be reset after the data was made: peaks include making the data)")


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=8884, help="CVUSA-size setting: queries = references (0 skips)")
    parser.add_argument("--dim", type=int, default=4096)
    parser.add_argument("--large-n", type=int, default=1_000_000, help="large gallery size (0 skips)")
    parser.add_argument("--large-dim", type=int, default=512)
    parser.add_argument("--large-queries", type=int, default=1000)
    parser.add_argument("--noise", type=float, default=1.5, help="query noise (latent std), CVUSA-size setting")
    parser.add_argument("--large-noise", type=float, default=1.0, help="the same for the large gallery")
    parser.add_argument("--rank", type=int, default=64, help="intrinsic dimension of the synthetic descriptors")
    parser.add_argument("--train-points", type=int, default=65536, help="IVF-PQ training sample (>= 39 nlist)")
    parser.add_argument("--nlist", type=int, default=1024)
    parser.add_argument("--m", type=int, default=64)
    parser.add_argument("--nbits", type=int, default=8)
    parser.add_argument("--nprobe", type=int, nargs="+", default=[16, 64, 256], help="IVF lists visited per query")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--case", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.case:
        run_case(args)
    else:
        main(args, sys.argv[1:])
