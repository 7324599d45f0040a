"""Retrieval evaluation: time and peak memory of recall / gallery search, exact against the FAISS gallery kinds.

Two settings, each case in its own process so that its peak memory is its own:
1. CVUSA val size: N = 8,884 queries and references, D = 4,096 (the paper's descriptor size): recall_at_k with
   the exact torch backend and with the FAISS flat backend (the two must print the same recall).
2. A country-scale gallery: 1,000,000 references. 1M x 4,096 float32 is 16 GB, more than a shared 24 GB machine
   should hold, so the default is D = 512 (2 GB); pass --large-dim 4096 on a machine that has the memory.
   Exact search (torch, chunked) side by side with each approximate GalleryIndex kind in --kinds (ivfpq,
   pq_refine, ivfpq_refine, pq_sq8, ivfpq_disk, hnsw), each over a sweep of its search knob (--nprobe, --k-factor,
   --ef-search; ivfpq_disk is saved and loaded back first, so that it is searched with its float16 rows on disk):
   recall kept (approximate / exact R@1 and R@10), ms per query, index size (FAISS serialize_index bytes), the
   process's peak memory rise and the build time. Only --large-queries queries are timed (default 1,000); the
   gallery is full size. The load average (/proc/loadavg) is printed with each case: the CPU may be shared.

3. The largest gallery (--huge-n, e.g. 10,000,000 x 512: 19 GiB of float32, more than the process may hold): the
   compact kind (pq_sq8) built from a stream of blocks made from a seed, never the whole float data: the codebook
   trains on the first --train-points references, then block after block is made, added, and scored exactly against
   the queries (a running top-1, for the exact R@1), then dropped. The index is saved with GalleryIndex.save (FAISS
   write_index, straight to the file) and loaded memory-mapped (GalleryIndex.load), then timed one query at a time.
   Printed: build time, peak RSS, index file bytes, the RSS after the mapped load and after the searches, ms/query,
   and R@1 against the exact R@1.

Data: synthetic unit descriptors of intrinsic dimension --rank (64) in D dimensions, plus a little isotropic noise;
query i is reference i's latent code plus --noise (--large-noise) Gaussian noise, chosen so that exact recall is
high but not 100%. Peak memory is the rise of the process's peak RSS (VmHWM) over the RSS after the data was made.

    OMP_NUM_THREADS=1 python benchmarks/bench_eval.py --n 0             # 1M gallery: ~35 min on a busy core (hnsw
                                                                        # builds for ~25 of them)
    OMP_NUM_THREADS=1 python benchmarks/bench_eval.py --n 0 --kinds pq_refine ivfpq_refine  # ~5 min
    python benchmarks/bench_eval.py --large-n 0                         # CVUSA size only
    python benchmarks/bench_eval.py --large-n 200000 --large-queries 500  # quicker large setting
    OMP_NUM_THREADS=1 python benchmarks/bench_eval.py --n 0 --large-n 0 --huge-n 10000000  # the largest gallery
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np
from process_memory import load_average, mapped_rss, reset_peak, status_mib
from synthetic_descriptors import latent_map, make_data, stream_block


def run_huge(args):
    """The largest gallery: --huge-kind built from a stream of blocks (in --huge-shards shards, each saved, then
    merged as `geoloc gallery merge` does), saved, loaded memory-mapped, searched one query at a time."""
    import tempfile

    import faiss
    import torch

    from geoloc.eval import GalleryIndex

    torch.set_num_threads(args.threads)
    faiss.omp_set_num_threads(args.threads)
    n, dim, block, nq = args.huge_n, args.large_dim, 100_000, args.huge_queries
    w = latent_map(dim, args.seed, args.rank)
    rng = np.random.default_rng([args.seed, 2**40])  # the queries: a stream of their own
    z0, _ = stream_block(w, 0, min(block, n), args.seed)
    query = (z0[:nq] + args.large_noise * rng.standard_normal((nq, w.shape[0]), dtype=np.float32)) @ w
    query /= np.linalg.norm(query, axis=1, keepdims=True)
    knobs = (dict(coarse_m=args.coarse_m) if args.huge_kind == "pq_sq8" else
             dict(nlist=args.nlist, m=args.m, nprobe=args.huge_nprobe[0]))
    codebook = GalleryIndex(dim, backend="faiss", kind=args.huge_kind, k_factor=IVF_K_FACTOR, **knobs)
    base = status_mib("VmRSS")
    exact_peak = reset_peak()
    start = time.perf_counter()
    codebook.train(stream_block(w, 0, min(args.train_points, n), args.seed)[1])
    best = np.full(nq, -np.inf, np.float32)
    best_row = np.zeros(nq, np.int64)
    exact_s = 0.0
    bounds = [block * round(i * n / block / args.huge_shards) for i in range(args.huge_shards)] + [n]
    with tempfile.TemporaryDirectory(dir=args.huge_dir) as tmp:
        parts = []
        for i, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:])):
            part = codebook.trained_empty() if args.huge_shards > 1 else codebook
            for s in range(lo, hi, block):
                _, ref = stream_block(w, s, min(s + block, hi), args.seed)
                part.add(ref)
                t = time.perf_counter()
                scores = query @ ref.T  # the exact top-1, block by block (the lower row wins a tie)
                top = scores.argmax(1)
                better = scores[np.arange(nq), top] > best
                best[better], best_row[better] = scores[np.arange(nq), top][better], s + top[better]
                exact_s += time.perf_counter() - t
            if args.huge_shards > 1:  # a shard job's folder
                os.makedirs(os.path.join(tmp, f"shard{i}"))
                part.save(os.path.join(tmp, f"shard{i}", "gallery.pt"))
                parts.append(os.path.join(tmp, f"shard{i}", "gallery.pt"))
                del part
        merge_s = 0.0
        if parts:
            t = time.perf_counter()
            index = GalleryIndex.load(parts[0], mmap=False)
            for part in parts[1:]:
                index.merge(GalleryIndex.load(part, mmap=False))
            merge_s = time.perf_counter() - t
        else:
            index = codebook
        del codebook
        build_s = time.perf_counter() - start - exact_s
        res = {"case": "huge", "kind": args.huge_kind, "shards": args.huge_shards, "n_ref": n, "dim": dim,
               "n_query": nq, "build_s": build_s, "merge_s": merge_s,
               "build_peak_rise_mib": status_mib("VmHWM") - base, "peak_is_exact": exact_peak,
               "exact_recall": {"R@1": float(np.mean(best_row == np.arange(nq)))}}
        folder = os.path.join(tmp, "gallery")
        os.makedirs(folder)
        path = os.path.join(folder, "gallery.pt")
        t = time.perf_counter()
        index.save(path)
        res["save_s"] = time.perf_counter() - t
        res["index_bytes"] = os.path.getsize(os.path.join(folder, "gallery.faiss"))
        res["rows_bytes"] = sum(os.path.getsize(os.path.join(folder, f)) for f in os.listdir(folder)
                                if f.endswith(".f16"))
        del index
        before_load = {k: status_mib(k) for k in ("RssAnon", "RssFile")}
        loaded, res["load_s"] = timed(lambda: GalleryIndex.load(path))
        res["rss_after_load_mib"] = sum(status_mib(k) - before_load[k] for k in before_load)
        def searched(nprobe):  # the nq queries one at a time -> {nprobe, ms_per_query, recall}
            rows = np.zeros((nq, 10), np.int64)
            t = time.perf_counter()
            for i in range(nq):
                rows[i] = loaded.search(query[i:i + 1], 10)[1][0].numpy()
            return {"nprobe": nprobe, "ms_per_query": 1e3 * (time.perf_counter() - t) / nq,
                    "recall": recall_from_topk(rows)}

        res["sweep"] = [searched(args.huge_nprobe[0])]
        res["ms_per_query"], res["recall"] = res["sweep"][0]["ms_per_query"], res["sweep"][0]["recall"]
        res["rss_after_search_mib"] = sum(status_mib(k) - before_load[k] for k in before_load)
        res["own_after_search_mib"] = status_mib("RssAnon") - before_load["RssAnon"]
        res["mapped_after_search_mib"] = mapped_rss(folder)
        for nprobe in args.huge_nprobe[1:] if args.huge_kind == "ivfpq_disk" else ():  # the same loaded gallery
            loaded.set_search_params(nprobe=nprobe)
            res["sweep"].append(searched(nprobe))
    res["peak_mib"] = status_mib("VmHWM") - base
    res["load"] = load_average()
    print(json.dumps(res))


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def run_case(args):
    """Child process: one case; prints one JSON line."""
    import torch

    torch.set_num_threads(args.threads)
    from geoloc.eval import GalleryIndex, recall_at_k

    if args.case == "huge":
        return run_huge(args)
    small = args.case.startswith("small")
    n_ref = args.n if small else args.large_n
    n_query = args.n if small else args.large_queries
    dim = args.dim if small else args.large_dim
    query, ref = make_data(n_ref, n_query, dim, args.noise if small else args.large_noise, args.seed,
                             rank=args.rank)
    base = status_mib("VmRSS")
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
        res["index_mib"] = ref.nbytes / 2**20
        (_, idx), res["time_s"] = timed(lambda: index.search(query, 10))
        res["recall"] = recall_from_topk(idx.numpy())
    else:
        res.update(run_approximate(args, args.case.removeprefix("large-"), query, ref))
    res["peak_mib"] = res.pop("peak_before_size_mib", status_mib("VmHWM")) - base
    res["peak_is_exact"] = exact_peak
    res["load"] = load_average()
    print(json.dumps(res))


SWEPT = {"ivfpq": "nprobe", "pq_refine": "k_factor", "ivfpq_refine": "nprobe", "pq_sq8": "k_factor",
         "ivfpq_disk": "nprobe", "hnsw": "ef_search"}
IVF_K_FACTOR = 16  # ivfpq_refine sweeps nprobe at this shortlist multiple


def run_approximate(args, kind, query, ref):
    """Build one FAISS kind, then search with each value of its swept knob (--repeat times each)."""
    import faiss

    from geoloc.eval import GalleryIndex

    faiss.omp_set_num_threads(args.threads)
    index = GalleryIndex(ref.shape[1], backend="faiss", kind=kind, nlist=args.nlist, m=args.m, nbits=args.nbits,
                         coarse_m=args.coarse_m, k_factor=IVF_K_FACTOR, hnsw_m=args.hnsw_m,
                         ef_construction=args.ef_construction)
    def build():
        index.train(ref, max_points=args.train_points)
        index.add(ref)

    build_s = timed(build)[1]
    disk = {}
    if kind == "ivfpq_disk":  # searched as a saved gallery is: the codes in memory, the float16 rows mapped
        folder = saved(index, args)
        del index
        index, disk = reopened(folder)
    knob = SWEPT[kind]
    sweep = []
    for value in getattr(args, knob):
        index.set_search_params(**{knob: value})
        times = []
        for _ in range(args.repeat):
            (_, idx), time_s = timed(lambda: index.search(query, 10))
            times.append(time_s)
        sweep.append(dict(knob=knob, value=value, times_s=times, recall=recall_from_topk(idx.numpy())))
    peak = status_mib("VmHWM")  # before serialize_index makes its copy
    if disk:
        before = disk.pop("rss_before_load")
        disk["rss_after_search_mib"] = {**{k: status_mib(k) - before[k] for k in before}, **mapped_rss(disk["folder"])}
    return dict(build_s=build_s, sweep=sweep, peak_before_size_mib=peak,
                index_mib=len(faiss.serialize_index(index._index)) / 2**20, **disk)


def saved(index, args):
    import tempfile

    folder = tempfile.mkdtemp(dir=args.huge_dir)
    index.save(os.path.join(folder, "gallery.pt"))
    return folder


def reopened(folder):
    """ivfpq_disk: the index saved in `folder` loaded back (its codes and float16 rows memory-mapped); the resident
    memory the load adds, and the bytes of the rows' files."""
    from geoloc.eval import GalleryIndex

    rows = sum(os.path.getsize(os.path.join(folder, f)) for f in os.listdir(folder) if f.endswith(".f16"))
    before = {k: status_mib(k) for k in ("RssAnon", "RssFile")}  # memory of its own; pages of mapped files
    loaded = GalleryIndex.load(os.path.join(folder, "gallery.pt"))
    return loaded, {"rss_before_load": before, "rss_after_load_mib": {k: status_mib(k) - before[k] for k in before},
                    "rows_file_mib": rows / 2**20, "folder": folder}


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
    return " / ".join(f"{100 * v:5.1f}" for v in r.values())


def describe(kind, args):
    return {"ivfpq": f"nlist {args.nlist} m {args.m}x{args.nbits}", "pq_refine": f"m {args.m}x4",
            "ivfpq_refine": f"nlist {args.nlist} m {args.m}x4 k_factor {IVF_K_FACTOR}",
            "pq_sq8": f"m {args.coarse_m}x4 + SQ8", "hnsw": f"M {args.hnsw_m} efC {args.ef_construction}",
            "ivfpq_disk": f"nlist {args.nlist} m {args.m}x4 + f16 rows k_factor {IVF_K_FACTOR}"}[kind]


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
            print(f"  {case:12s} {r['time_s']:7.2f} s   peak +{r['peak_mib']:7.0f} MiB   R@1 / R@5 / R@10 "
                  f"{fmt_recall(r['recall'])}   load avg {r['load']}")
    if args.large_n:
        print(f"\n[2] large gallery: {args.large_n:,} references, D = {args.large_dim} ({args.large_n:,} x 4,096 "
              f"float32 would take {args.large_n * 4096 * 4 / 2**30:.1f} GiB), {args.large_queries:,} queries, top-10; "
              f"{args.threads} thread(s); search times: best of {args.repeat} (worst in brackets)")
        print(f"  {'index':60s} {'ms/query':>16s} {'R@1 kept':>8s} {'R@10 kept':>9s} {'index MiB':>9s} "
              f"{'peak rise':>9s} {'build s':>7s}  R@1 / R@5 / R@10 (%)   load avg")
        exact = spawn("large-exact", argv)
        results.append(exact)
        ms = 1e3 / args.large_queries
        print(f"  {'exact (torch, chunked)':60s} {ms * exact['time_s']:8.2f}{'':8s} {'100%':>8s} {'100%':>9s} "
              f"{exact['index_mib']:9.0f} {exact['peak_mib']:9.0f} {'-':>7s}  {fmt_recall(exact['recall'])}   "
              f"{exact['load']}")
        for kind in args.kinds:
            r = spawn(f"large-{kind}", argv)
            results.append(r)
            for i, p in enumerate(r["sweep"]):
                name = f"{kind} {describe(kind, args)}, {p['knob']} {p['value']}"
                best, worst = min(p["times_s"]), max(p["times_s"])
                spread = f"({ms * worst:.2f})" if len(p["times_s"]) > 1 else ""
                kept = [f"{100 * p['recall'][k] / exact['recall'][k]:.1f}%" if exact["recall"][k] else "-"
                        for k in ("R@1", "R@10")]
                sizes = (f"{r['index_mib']:9.0f} {r['peak_mib']:9.0f} {r['build_s']:7.0f}" if i == 0
                         else f"{'':9s} {'':9s} {'':7s}")
                print(f"  {name:60s} {ms * best:8.2f}{spread:>8s} {kept[0]:>8s} {kept[1]:>9s} {sizes}  "
                      f"{fmt_recall(p['recall'])}   {r['load'] if i == 0 else ''}")
            if "rows_file_mib" in r:
                load, search = r["rss_after_load_mib"], r["rss_after_search_mib"]
                print(f"  {'':4s}(loaded from disk, resident: +{load['RssAnon']:.0f} MiB own + {load['RssFile']:.0f} "
                      f"MiB of mapped pages after the load; after all the searches +{search['RssAnon']:.0f} MiB own, "
                      f"{search['.faiss']:.0f} MiB of the codes' pages and {search['.f16']:.0f} MiB of the float16 "
                      f"rows' pages, of {r['rows_file_mib']:.0f} MiB on disk)")
    if args.huge_n:
        r = spawn("huge", argv)
        results.append(r)
        kept = 100 * r["recall"]["R@1"] / r["exact_recall"]["R@1"]
        what = (f"pq_sq8 (m {args.coarse_m}x4 + SQ8" if r["kind"] == "pq_sq8" else
                f"ivfpq_disk (nlist {args.nlist} m {args.m}x4 + float16 rows, nprobe {args.huge_nprobe[0]}")
        mapped = r["mapped_after_search_mib"]
        print(f"\n[3] largest gallery: {what}, k_factor {IVF_K_FACTOR}), {r['n_ref']:,} references in "
              f"{r['shards']} shard(s), D = {r['dim']} ({r['n_ref'] * r['dim'] * 4 / 2**30:.1f} GiB of float32, "
              f"never held), {r['n_query']} queries one at a time, {args.threads} thread(s)\n"
              f"  build (train + add, streamed; merge {r['merge_s']:.0f} s) {r['build_s']:.0f} s, peak RSS rise "
              f"{r['build_peak_rise_mib']:.0f} MiB; index file {r['index_bytes'] / 2**30:.2f} GiB "
              f"({r['index_bytes'] / r['n_ref']:.1f} B a reference), float16 rows on disk "
              f"{r['rows_bytes'] / 2**30:.2f} GiB; save {r['save_s']:.0f} s, memory-mapped load {r['load_s']:.1f} s "
              f"(+{r['rss_after_load_mib']:.0f} MiB RSS, +{r['rss_after_search_mib']:.0f} MiB after the searches: "
              f"{r['own_after_search_mib']:.0f} own, {mapped['.faiss']:.0f} of the codes' pages, "
              f"{mapped['.f16']:.0f} of the rows' pages)\n"
              f"  {r['ms_per_query']:.2f} ms/query; R@1 {100 * r['recall']['R@1']:.1f}% against the exact "
              f"{100 * r['exact_recall']['R@1']:.1f}% ({kept:.1f}% kept)   load avg {r['load']}")
        for row in r["sweep"][1:]:
            r1 = row["recall"]["R@1"]
            print(f"  nprobe {row['nprobe']}: {row['ms_per_query']:.2f} ms/query; R@1 {100 * r1:.1f}% "
                  f"({100 * r1 / r['exact_recall']['R@1']:.1f}% kept)")
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
    parser.add_argument("--kinds", nargs="*", default=list(SWEPT), choices=list(SWEPT),
                        help="approximate kinds to compare with exact search (hnsw builds for ~25 min at 1M)")
    parser.add_argument("--train-points", type=int, default=65536, help="IVF / PQ training sample (>= 39 nlist)")
    parser.add_argument("--nlist", type=int, default=1024)
    parser.add_argument("--m", type=int, default=64)
    parser.add_argument("--coarse-m", type=int, default=32, help="pq_sq8: 4-bit sub-quantisers of the coarse code")
    parser.add_argument("--nbits", type=int, default=8, help="ivfpq bits per sub-code (the refine kinds use 4)")
    parser.add_argument("--nprobe", type=int, nargs="+", default=[16, 64, 256, 512], help="IVF lists visited per query")
    parser.add_argument("--k-factor", type=int, nargs="+", default=[4, 16], help="pq_refine shortlist multiple")
    parser.add_argument("--hnsw-m", type=int, default=32)
    parser.add_argument("--ef-construction", type=int, default=40)
    parser.add_argument("--ef-search", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--repeat", type=int, default=2, help="searches per setting (best and worst printed)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--huge-n", type=int, default=0, help="the largest gallery (streamed; 0 skips)")
    parser.add_argument("--huge-kind", default="pq_sq8", choices=["pq_sq8", "ivfpq_disk"])
    parser.add_argument("--huge-shards", type=int, default=1, help="built in this many shards, then merged")
    parser.add_argument("--huge-nprobe", type=int, nargs="+", default=[256],
                        help="ivfpq_disk: lists visited per query (several: each searched on the same loaded gallery)")
    parser.add_argument("--huge-queries", type=int, default=300, help="its queries, timed one at a time")
    parser.add_argument("--huge-dir", default=None, help="where its index file is written (default: the temp dir)")
    parser.add_argument("--case", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.case:
        run_case(args)
    else:
        main(args, sys.argv[1:])
