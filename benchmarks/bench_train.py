"""Training speed at the paper size: step pairs/s against loader pairs/s (does decoding keep up with the step?).

Paper size: batch 64, 288 x 288 for both branches (IPT street image and aerial), two unshared VGG16 (width 1.0)
+ MSAE, descriptor dim 4,096, GMS queue 1,024 (geoloc/conf/experiment/paper_cvusa.yaml). The model is random-initialised
(speed does not depend on the weights).

- step: one training step as the Trainer runs it (forward through the task, backward, Adam step, queue push) on
  a fixed batch already on the device; median of --steps after --warmup steps. On CUDA also: peak GPU memory, the
  step with its batch moved each time from pinned memory (and through the task's on-device preparation), and the
  places in geoloc where one step waits for the GPU (torch's sync debug mode).
- loader: the Trainer's DataLoader (EpochSampler, --workers workers, pinned memory on CUDA) over a CVUSA-layout
  dataset, decode + IPT + augmentation included; pairs/s over --loader-batches batches after the first.
- fit (--fit): `Trainer.fit` over the step's items (decoded once, held in memory and repeated to --fit-pairs pairs
  an epoch), --fit-epochs epochs, no validation; every epoch writes last.pt and best.pt, as an improving epoch does.
  Pairs/s over the epochs after the first (which pays for start-up and compiling), beside the step's, and the time
  between epochs: from an epoch's last step to the next epoch's first (minus one step). --writer sync-twice
  writes as the trainer did before: last.pt and best.pt each serialised, in the training thread.

    OMP_NUM_THREADS=1 python benchmarks/bench_train.py --batch 2 --steps 2 --workers 1         # CPU, a few minutes
    python benchmarks/bench_train.py --device cuda --workers 8                                  # fp32, batch 64
    python benchmarks/bench_train.py --device cuda --workers 8 --precision bf16 --channels-last [--compile]
    python benchmarks/bench_train.py --device cuda --workers 8 --skip-loader --fit [--writer sync-twice]
    OMP_NUM_THREADS=1 python benchmarks/bench_train.py --recipe default --skip-loader --fit --fit-pairs 64 \
        --batch 16 --workers 0                                              # the CPU's default recipe

Data: --root DIR (CVUSA layout, e.g. real CVUSA), else a synthetic one is generated once into --cache
(`python data_prep/synthetic.py --layout cvusa --out DIR --train 64 --val 8 --preset cvusa`).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.utils.data import default_collate

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from geoloc.launch.hydra_hooks import compose_conf  # noqa: E402
from geoloc.engine import Trainer  # noqa: E402
from geoloc.engine import checkpoint as ckpt_io  # noqa: E402
from geoloc.tasks.crossview import build_run  # noqa: E402
from bench_overhead import HeldItems  # noqa: E402  (the items decoded once, the benchmark's)


def dataset_root(args) -> Path:
    if args.root:
        return Path(args.root)
    root = Path(args.cache)
    if not (root / "splits" / "train-19zl.csv").is_file():
        from geoloc.synthetic import generate

        print(f"generating a 64-pair CVUSA-size synthetic dataset into {root} ...", flush=True)
        generate("cvusa", str(root), 64, 8, seed=0, preset="cvusa", progress=False)
    return root


def config(args, root: Path, run_dir: Path):
    paper = getattr(args, "recipe", "paper") == "paper"  # the default recipe reads its embedded synthetic world
    recipe = ["experiment=paper_cvusa", "backbone.pretrained=false", f"dataset.root={root}"] if paper else []
    overrides = [*recipe,
                 f"dataset.batch_size={args.batch}", f"trainer.device={args.device}", f"trainer.num_workers={args.workers}",
                 f"trainer.precision={args.precision}", f"trainer.channels_last={args.channels_last}",
                 f"trainer.compile={args.compile}", "trainer.progress=false", f"run_dir={run_dir}"]
    return compose_conf("train", overrides)


def bench_step(cfg, trainer: Trainer, train_set, args) -> dict:
    task = build_run(cfg, "/tmp/geoloc_bench/run").task.to(trainer.device)
    if args.channels_last:
        task.to(memory_format=torch.channels_last)
    optimizer = task.configure_optimizers()[0][0]
    model = torch.compile(task) if args.compile else task
    items = [train_set[(i % len(train_set), 0)] for i in range(args.batch)]
    batch = trainer.engine.to_device(default_collate(items), task)
    times = []
    for i in range(args.warmup + args.steps):
        if trainer.device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        one_step(model, task, trainer, batch, optimizer)
        if trainer.device.type == "cuda":
            torch.cuda.synchronize()
        if i >= args.warmup:
            times.append(time.perf_counter() - t0)
        print(f"  step {i}: {time.perf_counter() - t0:.2f} s{' (warm-up)' if i < args.warmup else ''}", flush=True)
    step_s = statistics.median(times)
    result = {"step_s": step_s, "step_pairs_s": args.batch / step_s,
              "query_shape": tuple(batch["query"].shape), "reference_shape": tuple(batch["reference"].shape)}
    if trainer.device.type == "cuda":
        result["peak_gib"] = torch.cuda.max_memory_allocated() / 2**30
        result.update(step_with_transfer(model, task, trainer, items, optimizer, args))
        result["syncs_a_step"] = syncs_of_a_step(model, task, trainer, batch, optimizer)
    return result


def one_step(model, task, trainer: Trainer, batch: dict, optimizer) -> None:
    with trainer.autocast():
        out = model(batch, trainer.engine)
    trainer.engine.backward(out["loss"])
    trainer.engine.step(optimizer)
    task.on_train_batch_end(out)


def step_with_transfer(model, task, trainer: Trainer, items: list, optimizer, args) -> dict:
    """The step with its batch moved each time from pinned host memory (what the loader hands over) and through
    the task's on-device preparation, as fit does: median of --steps."""
    host = {k: v.pin_memory() if isinstance(v, torch.Tensor) else v for k, v in default_collate(items).items()}
    times = []
    for _ in range(args.steps):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        one_step(model, task, trainer, trainer.engine.to_device(host, task), optimizer)
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    step_s = statistics.median(times)
    return {"step_transfer_s": step_s, "step_transfer_pairs_s": args.batch / step_s}


def syncs_of_a_step(model, task, trainer: Trainer, batch: dict, optimizer) -> dict[str, int]:
    """Where one step waits for the GPU: torch's sync debug mode warns at each synchronising call; counted by the
    geoloc line that made it (the innermost frame in geoloc/)."""
    import traceback
    import warnings

    counts: dict[str, int] = {}

    def note(message, category, filename, lineno, file=None, line=None):
        frames = [f for f in traceback.extract_stack() if "/geoloc/" in f.filename]
        where = f"{Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else f"{filename}:{lineno}"
        counts[where] = counts.get(where, 0) + 1

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = note
        torch.cuda.set_sync_debug_mode("warn")
        try:
            one_step(model, task, trainer, batch, optimizer)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    torch.cuda.synchronize()
    return counts


class EveryEpochBest:
    """The trainer's writer, told that every epoch improved: each epoch writes last.pt and best.pt."""

    def __init__(self, writer, run_dir: Path):
        self.writer, self.best = writer, run_dir / "best.pt"

    def submit(self, state, path, also=()):
        self.writer.submit(state, path, also=(self.best,))

    def join(self):
        self.writer.join()


class SerialisedTwice:
    """How the trainer wrote before: each file serialised, fsynced and renamed in the training thread."""

    def submit(self, state, path, also=()):
        for target in (path, *also):
            ckpt_io.save_atomic(state, target)

    def join(self):
        pass


class NoWrites:
    """No checkpoint at all: what the epochs cost without the writer."""

    def submit(self, state, path, also=()):
        pass

    def join(self):
        pass


class EpochClock:
    """Times of the task's hooks, read around the trainer: each epoch's start and each step's end (synchronised
    with the GPU at an epoch's first and last step, so a time is the work's, not its launch's)."""

    def __init__(self, task, trainer: Trainer, steps_per_epoch: int):
        self.starts, self.first_ends, self.last_ends, self.first_batches = {}, {}, {}, {}
        self.sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
        step_end, epoch_start = task.on_train_batch_end, task.on_train_epoch_start
        counts: dict[int, int] = {}

        def on_train_epoch_start(engine):
            self.starts[engine.epoch] = time.perf_counter()
            epoch_start(engine)

        def on_train_batch_end(outputs):
            step_end(outputs)
            epoch = trainer.epoch
            counts[epoch] = counts.get(epoch, 0) + 1
            if counts[epoch] in (1, steps_per_epoch):
                self.sync()
                (self.first_ends if counts[epoch] == 1 else self.last_ends)[epoch] = time.perf_counter()

        task.on_train_epoch_start, task.on_train_batch_end = on_train_epoch_start, on_train_batch_end
        make_loader = task.train_dataloader
        task.train_dataloader = lambda *args: TimedLoader(make_loader(*args), self, trainer)


class TimedLoader:
    """A loader that notes when each epoch's first batch comes out of it."""

    def __init__(self, loader, clock: EpochClock, trainer: Trainer):
        self.loader, self.clock, self.trainer = loader, clock, trainer

    def __getattr__(self, name):
        return getattr(self.__dict__["loader"], name)

    def __len__(self):
        return len(self.loader)

    def __iter__(self):
        for i, batch in enumerate(self.loader):
            if i == 0:
                self.clock.first_batches[self.trainer.epoch] = time.perf_counter()
            yield batch


def bench_fit(cfg, train_set, args, step_s: float | None) -> dict:
    run_dir = Path(tempfile.mkdtemp(prefix="geoloc_bench_fit_"))
    run = build_run(cfg, run_dir)
    task, trainer = run.task, run.trainer
    pairs = HeldItems(train_set, min(len(train_set), args.fit_pairs), args.fit_pairs)
    writer = {"background": ckpt_io.CheckpointWriter, "sync-twice": SerialisedTwice, "none": NoWrites}[args.writer]()
    trainer.writer = EveryEpochBest(writer, run_dir)
    steps = len(pairs) // args.batch
    clock = EpochClock(task, trainer, steps)
    t0 = time.perf_counter()
    trainer.fit(task, pairs, None, args.batch)
    total_s = time.perf_counter() - t0
    epochs = sorted(clock.last_ends)
    timed = clock.last_ends[epochs[-1]] - clock.last_ends[epochs[0]]  # the epochs after the first, gaps included
    gaps = [clock.first_ends[e + 1] - clock.last_ends[e] for e in epochs[:-1]]
    to_start = [clock.starts[e + 1] - clock.last_ends[e] for e in epochs[:-1]]
    to_batch = [clock.first_batches[e + 1] - clock.starts[e + 1] for e in epochs[:-1]]
    result = {"fit_pairs_s": steps * args.batch * (len(epochs) - 1) / timed, "fit_total_s": total_s,
              "between_epochs_s": statistics.median(gaps), "last_step_to_epoch_start_s": statistics.median(to_start),
              "epoch_start_to_first_batch_s": statistics.median(to_batch),
              "fit_steps_per_epoch": steps, "writer": args.writer,
              "checkpoint_mb": (run_dir / "last.pt").stat().st_size / 1e6 if (run_dir / "last.pt").exists() else 0.0}
    if step_s is not None:
        result["idle_between_epochs_s"] = max(0.0, result["between_epochs_s"] - step_s)
    return result


def bench_loader(trainer: Trainer, train_set, args) -> dict:
    loader = trainer.loader(train_set, args.batch, train=True)
    pairs, t0, epoch = 0, None, 0
    while True:  # epochs until --loader-batches batches were timed
        loader.sampler.set_epoch(epoch)
        for batch in loader:
            if t0 is None:  # the first batch pays for worker start-up
                t0 = time.perf_counter()
                continue
            pairs += batch["query"].shape[0]
            if pairs >= args.loader_batches * args.batch:
                return {"loader_pairs_s": pairs / (time.perf_counter() - t0)}
        epoch += 1


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--batch", type=int, default=64, help="pairs per step (paper: 64; use 2-4 on a CPU)")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--workers", type=int, default=4, help="DataLoader workers")
    p.add_argument("--loader-batches", type=int, default=16)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--precision", default="32", choices=["32", "bf16", "16"])
    p.add_argument("--channels-last", action="store_true")
    p.add_argument("--compile", action="store_true")
    p.add_argument("--root", default=None, help="a CVUSA-layout dataset (default: a generated synthetic one)")
    p.add_argument("--cache", default="/tmp/geoloc_bench/cvusa64")
    p.add_argument("--skip-step", action="store_true")
    p.add_argument("--skip-loader", action="store_true")
    p.add_argument("--recipe", default="paper", choices=["paper", "default"],
                   help="paper: experiment=paper_cvusa (backbone.pretrained=false); default: `python train.py`'s")
    p.add_argument("--fit", action="store_true", help="also Trainer.fit over the step's items (see above)")
    p.add_argument("--fit-pairs", type=int, default=2048, help="fit: pairs an epoch")
    p.add_argument("--fit-epochs", type=int, default=3, help="fit: epochs (the first is not timed)")
    p.add_argument("--writer", default="background", choices=["background", "sync-twice", "none"],
                   help="fit: the trainer's checkpoint writer, the one it had before (sync-twice), or none")
    args = p.parse_args(argv)

    root = dataset_root(args) if args.recipe == "paper" else "the default recipe's embedded world"
    cfg = config(args, root, Path("/tmp/geoloc_bench/run"))
    cfg.trainer.max_epochs = args.fit_epochs
    run = build_run(cfg, "/tmp/geoloc_bench/run")  # as train.py builds it: task, trainer, data
    trainer, train_set = run.trainer, run.train_set
    print(f"device {trainer.device}, precision {args.precision}, channels_last {args.channels_last}, compile "
          f"{args.compile}, batch {args.batch}, workers {args.workers}, torch threads {torch.get_num_threads()}, "
          f"data {root} ({len(train_set)} pairs)", flush=True)
    result = {}
    if not args.skip_loader:
        result.update(bench_loader(trainer, train_set, args))
        print(f"loader: {result['loader_pairs_s']:.1f} pairs/s with {args.workers} workers", flush=True)
    if not args.skip_step:
        result.update(bench_step(cfg, trainer, train_set, args))
        mem = f", peak GPU memory {result['peak_gib']:.1f} GiB" if "peak_gib" in result else ""
        print(f"step: {result['step_s']:.2f} s = {result['step_pairs_s']:.2f} pairs/s (query "
              f"{result['query_shape']}, reference {result['reference_shape']}){mem}")
        if "step_transfer_pairs_s" in result:
            print(f"step with its batch moved from pinned memory: {result['step_transfer_pairs_s']:.2f} pairs/s; "
                  f"syncs a step: {sum(result['syncs_a_step'].values())} {result['syncs_a_step']}", flush=True)
    if args.fit:
        result.update(bench_fit(cfg, train_set, args, result.get("step_s")))
        ratio = f", fit / step = {result['fit_pairs_s'] / result['step_pairs_s']:.3f}" if "step_pairs_s" in result else ""
        if "step_transfer_pairs_s" in result:
            ratio += f", fit / step with transfer = {result['fit_pairs_s'] / result['step_transfer_pairs_s']:.3f}"
        idle = (f", idle {result['idle_between_epochs_s']:.2f} s beyond one step" if "idle_between_epochs_s" in result
                else "")
        print(f"fit: {result['fit_pairs_s']:.2f} pairs/s over epochs 1-{args.fit_epochs - 1} of "
              f"{result['fit_steps_per_epoch']} steps{ratio}; writer {args.writer}, checkpoint "
              f"{result['checkpoint_mb']:.0f} MB; last step -> next epoch's first step "
              f"{result['between_epochs_s']:.2f} s (to the epoch's start {result['last_step_to_epoch_start_s']:.2f} s, "
              f"then to its first batch {result['epoch_start_to_first_batch_s']:.2f} s)"
              f"{idle}", flush=True)
    if "loader_pairs_s" in result and "step_pairs_s" in result:
        ratio = result["loader_pairs_s"] / result["step_pairs_s"]
        print(f"loader / step = {ratio:.1f} ({'keeps up' if ratio >= 1 else 'the loader is the bottleneck'})")
    return result


if __name__ == "__main__":
    main()
