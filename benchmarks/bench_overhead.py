"""What geoloc's engine costs over plain PyTorch: the trainer against a bare loop, exact recall against a bare matmul.

Both cases run in one process, in alternating rounds (geoloc, bare, geoloc, bare...) so both see the same load, and
print the median time of each and their ratio, and the ratio of the fastest rounds (the least disturbed by other
load). The target is <= 1.05x for both (issue 21).

- train: `Trainer.fit` over the default recipe (`python train.py`: 64 px, VGG16-BN 1/8 width + MSAE, GMS triplet)
  against a hand-written loop over the same model, loss and optimiser: shuffle, collate, normalise, forward,
  backward, Adam step, the GMS queue push, the scheduler per epoch. The training items are decoded once and held
  in memory (the same items for both), so the figure is the engine's cost, not the decoder's (bench_loader.py
  measures that). The trainer's own work is all included: its seeded sampler, the finite-loss check, the logger,
  the progress bookkeeping and the atomic checkpoint write after each epoch.
- eval: `geoloc.eval.retrieval_metrics` (the one scorer: R@1, R@5, R@10, R@1%, descriptors checked) at CVUSA's
  size (8,884 x 8,884, D 4,096; bench_eval.py's low-rank unit descriptors, synthetic_descriptors.py, the query a
  noisy copy) against a bare chunked `q @ r.T` with a count of the references above the positive.

    OMP_NUM_THREADS=1 python benchmarks/bench_overhead.py                      # both cases, 1 thread
    OMP_NUM_THREADS=1 python benchmarks/bench_overhead.py --cases eval --rounds 5
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.utils.data import Dataset, default_collate

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from geoloc.launch.hydra_hooks import compose_conf  # noqa: E402
from geoloc.eval.retrieval_metrics import retrieval_metrics  # noqa: E402
from geoloc.eval.scoring import QUERY_CHUNK  # noqa: E402
from geoloc.tasks.crossview import build_run  # noqa: E402
from geoloc.tasks.crossview.transforms import normalised  # noqa: E402


class HeldItems(Dataset):
    """The first `n` training pairs' items of epoch 0, decoded once, repeated to `length` items (default `n`: an
    epoch of the size asked for without decoding it); the pairs' other attributes (split, labels) as they are."""

    def __init__(self, pairs, n: int, length: int | None = None):
        self.pairs = pairs
        self.items = [pairs[(i, 0)] for i in range(n)]
        self.length = n if length is None else length

    def __len__(self):
        return self.length

    def __getitem__(self, key):
        return self.items[(key[0] if isinstance(key, tuple) else key) % len(self.items)]

    def __getattr__(self, name):
        return getattr(self.__dict__["pairs"], name)


def train_config(args, run_dir: Path):
    overrides = ["trainer.progress=false", "trainer.num_workers=0", f"trainer.max_epochs={args.epochs}",
                 "sampler=shuffle", f"run_dir={run_dir}"]
    return compose_conf("train", overrides)


def geoloc_fit(cfg, items, run_dir: Path) -> float:
    run = build_run(cfg, run_dir)  # seeded, as train.py builds it
    t0 = time.perf_counter()
    run.trainer.fit(run.task, items, None, cfg.dataset.batch_size)
    return time.perf_counter() - t0


def bare_fit(cfg, items, run_dir: Path) -> float:
    """The same model, loss and optimiser in a plain loop: what a researcher would write without a framework."""
    task = build_run(cfg, run_dir).task  # the same seed, model, loss and optimiser as geoloc_fit's
    (optimizer,), schedulers = task.configure_optimizers()
    model, loss_fn, batch_size = task.model, task.loss, cfg.dataset.batch_size
    generator = torch.Generator().manual_seed(0)
    t0 = time.perf_counter()
    for epoch in range(cfg.trainer.max_epochs):
        if hasattr(loss_fn, "on_train_epoch_start"):
            loss_fn.on_train_epoch_start(epoch)
        model.train()
        order = torch.randperm(len(items), generator=generator).tolist()
        for start in range(0, len(order) - batch_size + 1, batch_size):
            batch = normalised(default_collate([items[i] for i in order[start:start + batch_size]]))
            query, reference = model(batch["query"], batch["reference"])
            loss = loss_fn(query, reference, batch["label"])
            loss = loss["loss"] if isinstance(loss, dict) else loss
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            if hasattr(loss_fn, "on_train_batch_end"):
                loss_fn.on_train_batch_end()
        for s in schedulers:
            s.step()
    return time.perf_counter() - t0


def run_train(args) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="geoloc_bench_overhead_"))
    cfg = train_config(args, tmp / "config")
    pairs = build_run(cfg, tmp / "config").train_set
    items = HeldItems(pairs, min(args.pairs or len(pairs), len(pairs)))
    steps = len(items) // cfg.dataset.batch_size * args.epochs
    print(f"train: the default recipe, {len(items)} pairs held in memory, batch {cfg.dataset.batch_size}, "
          f"{args.epochs} epochs = {steps} steps per round", flush=True)
    times = {"geoloc": [], "bare": []}
    geoloc_fit(cfg, items, tmp / "warm-up"), bare_fit(cfg, items, tmp / "warm-up-bare")  # first-call costs, untimed
    for r in range(args.rounds):
        times["geoloc"].append(geoloc_fit(cfg, items, tmp / f"run{r}"))
        times["bare"].append(bare_fit(cfg, items, tmp / f"bare{r}"))
        print(f"  round {r}: trainer {times['geoloc'][-1]:.2f} s, bare loop {times['bare'][-1]:.2f} s", flush=True)
    return summary("train", times)


def bare_recall(query: torch.Tensor, reference: torch.Tensor, ks) -> dict:
    """Chunked scores and a count of the references above each query's positive (reference i for query i)."""
    ranks = []
    for q0 in range(0, query.shape[0], QUERY_CHUNK):
        scores = query[q0:q0 + QUERY_CHUNK] @ reference.t()
        rows = torch.arange(scores.shape[0])
        positive = scores[rows, rows + q0]
        ranks.append((scores > positive[:, None]).sum(1))
    ranks = torch.cat(ranks)
    return {f"R@{k}": float((ranks < k).double().mean()) for k in ks}


def run_eval(args) -> dict:
    from synthetic_descriptors import make_data  # bench_eval.py's descriptors: a low intrinsic dimension, as learned

    query, reference = (torch.from_numpy(a) for a in make_data(args.n, args.n, args.dim, args.noise, seed=0))
    ks = (1, 5, 10, max(1, args.n // 100))
    print(f"eval: {args.n} x {args.n} unit descriptors, D {args.dim}, float32, query chunk {QUERY_CHUNK}", flush=True)
    times = {"geoloc": [], "bare": []}
    for r in range(args.rounds):
        t0 = time.perf_counter()
        ours = retrieval_metrics(query, reference)
        times["geoloc"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        bare = bare_recall(query, reference, ks)
        times["bare"].append(time.perf_counter() - t0)
        print(f"  round {r}: retrieval_metrics {times['geoloc'][-1]:.2f} s, bare matmul + count "
              f"{times['bare'][-1]:.2f} s", flush=True)
    same = [ours[key] == bare[f"R@{k}"] for key, k in zip(("R@1", "R@5", "R@10", "R@1%"), ks)]
    print(f"  the same recall: {all(same)} (geoloc R@1 {ours['R@1']:.4f}, bare {bare['R@1']:.4f})")
    return summary("eval", times)


def summary(case: str, times: dict) -> dict:
    ours, bare = statistics.median(times["geoloc"]), statistics.median(times["bare"])
    return {"case": case, "geoloc_s": ours, "bare_s": bare, "ratio": ours / bare,
            "best_ratio": min(times["geoloc"]) / min(times["bare"])}


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cases", nargs="+", default=["train", "eval"], choices=["train", "eval"])
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--epochs", type=int, default=2, help="train: epochs per round")
    p.add_argument("--pairs", type=int, default=0,
                   help="train: training pairs held in memory (0: the whole split, 1,200)")
    p.add_argument("--n", type=int, default=8884, help="eval: queries = references (CVUSA's test split)")
    p.add_argument("--dim", type=int, default=4096, help="eval: descriptor size (the paper's)")
    p.add_argument("--noise", type=float, default=2.0, help="eval: query noise in the latent space (R@1 about 0.4)")
    args = p.parse_args(argv)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); median of {args.rounds} alternating "
          "rounds", flush=True)
    results = [run_train(args) if case == "train" else run_eval(args) for case in args.cases]
    print("\n| case | geoloc s (median) | bare s (median) | geoloc / bare, medians | geoloc / bare, fastest rounds |"
          "\n|---|---|---|---|---|")
    for r in results:
        print(f"| {r['case']} | {r['geoloc_s']:.2f} | {r['bare_s']:.2f} | {r['ratio']:.3f} | {r['best_ratio']:.3f} |")
    return results


if __name__ == "__main__":
    main()
