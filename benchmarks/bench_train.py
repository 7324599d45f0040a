"""Training speed at the paper size: step pairs/s against loader pairs/s (does decoding keep up with the step?).

Paper size: batch 64, 288 x 288 for both branches (IPT street image and aerial), two unshared VGG16 (width 1.0)
+ MSAE, descriptor dim 4,096, GMS queue 1,024 (conf/experiment/paper_cvusa.yaml). The model is random-initialised
(speed does not depend on the weights).

- step: one training step as the Trainer runs it (forward through the task, backward, Adam step, queue push) on
  a fixed batch already on the device; median of --steps after --warmup steps. On CUDA: peak GPU memory too.
- loader: the Trainer's DataLoader (EpochSampler, --workers workers, pinned memory on CUDA) over a CVUSA-layout
  dataset, decode + IPT + augmentation included; pairs/s over --loader-batches batches after the first.

    OMP_NUM_THREADS=1 python benchmarks/bench_train.py --batch 2 --steps 2 --workers 1         # CPU, a few minutes
    python benchmarks/bench_train.py --device cuda --workers 8                                  # fp32, batch 64
    python benchmarks/bench_train.py --device cuda --workers 8 --precision bf16 --channels-last [--compile]

Data: --root DIR (CVUSA layout, e.g. real CVUSA), else a synthetic one is generated once into --cache
(`python data_prep/synthetic.py --layout cvusa --out DIR --train 64 --val 8 --preset cvusa`).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.utils.data import default_collate

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from geoloc.config import checked  # noqa: E402
from geoloc.launch.hydra_hooks import compose_conf  # noqa: E402
from geoloc.tasks.crossview.config import parse_training  # noqa: E402
from geoloc.tasks.crossview.data_config import parse_dataset  # noqa: E402
from geoloc.tasks.crossview.datasets import build  # noqa: E402
from geoloc.engine import Trainer, TrainerConfig, seed_everything  # noqa: E402
from geoloc.tasks.crossview.run import build_task  # noqa: E402


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
    overrides = ["experiment=paper_cvusa", "backbone.pretrained=false", f"dataset.root={root}",
                 f"dataset.batch_size={args.batch}", f"trainer.device={args.device}", f"trainer.num_workers={args.workers}",
                 f"trainer.precision={args.precision}", f"trainer.channels_last={args.channels_last}",
                 f"trainer.compile={args.compile}", "trainer.progress=false", f"run_dir={run_dir}"]
    return compose_conf("train", overrides)


def bench_step(cfg, trainer: Trainer, train_set, args) -> dict:
    seed_everything(0)
    run = parse_training(cfg)
    task = build_task(run.model, run.components, run.trainer.max_epochs).to(trainer.device)
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
        with trainer.autocast():
            out = model(batch, trainer.engine)
        trainer.engine.backward(out["loss"])
        trainer.engine.step(optimizer)
        task.on_train_batch_end(out)
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
    args = p.parse_args(argv)

    root = dataset_root(args)
    cfg = config(args, root, Path("/tmp/geoloc_bench/run"))
    trainer = Trainer(checked(cfg.trainer, TrainerConfig, "trainer"), "/tmp/geoloc_bench/run")
    train_set = build(*parse_dataset(cfg.dataset), "train", train=True)
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
    if "loader_pairs_s" in result and "step_pairs_s" in result:
        ratio = result["loader_pairs_s"] / result["step_pairs_s"]
        print(f"loader / step = {ratio:.1f} ({'keeps up' if ratio >= 1 else 'the loader is the bottleneck'})")
    return result


if __name__ == "__main__":
    main()
