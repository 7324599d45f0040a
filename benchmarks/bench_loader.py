"""One data worker's pairs/s against the bare decode of the same JPEGs, at the paper's, the default's and VIGOR's sizes.

Per case, in one process on one core (OMP_NUM_THREADS=1, cv2.setNumThreads(1), torch 1 thread: what one DataLoader
worker has), alternating rounds of:
- bare: cv2.imread of the pair's two files at full size, nothing else;
- loader: the cross-view training pairs' __getitem__ (CrossViewPairs, train=True: decode, checks, augmentation,
  alignment, and the worker's share of the tensor encoding), keys (index, epoch) cycling over the files;
and reports the median pairs/s of each, their ratio, the per-pair profile of the loader's stages, and the cost of
the batched normalisation that now runs on the training device (timed here on the CPU, per pair).

Cases (the dataset section each experiment composes):
- paper: experiment=paper_cvusa (IPT 288x288, rotation 10, no jitter) on 750x750 aerial / 1232x224 panorama JPEGs:
  the real CVUSA samples (REALDATA, beside the checkout) when present (5 pairs, cycled), else synthetic ones;
  (the 375 -> 288 resize of the half-scale aerial bilinear, dataset.resize_interpolation=linear as the real
  datasets' yaml set it); paper-area: the same with the area resize (INTER_AREA), as before;
- default: `python train.py`'s dataset keys (IPT 64x64, flip/rotate, jitter 0.1, reduced_decode=false) on the
  synthetic world's 256x256 aerial / 616x112 panorama JPEGs; default-reduced: the same with reduced_decode=true;
- vigor: dataset=vigor's keys at the paper's 288 (IPT 288x288, flip/rotate, jitter 0.1) on VIGOR's 640x640 PNG
  aerials and 2048x1024 JPEG panoramas;
- vigor-cpu: experiment=vigor_cpu's keys (IPT 64x64, flip/rotate) on the synthetic vigor layout's 256x256 PNG tiles
  and 512x256 JPEG panoramas; vigor-cpu-cached: the same with dataset.cache_decoded=true, each file decoded once
  (the rounds after the first reuse the kept arrays, as every epoch after the first does in training).
Synthetic files are smooth noise (so they compress like photos), written to a temporary folder.

    OMP_NUM_THREADS=1 python benchmarks/bench_loader.py                    # this checkout
    OMP_NUM_THREADS=1 python benchmarks/bench_loader.py --code DIR         # another checkout's code (e.g. main)
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
REALDATA = REPO.parent / "shared" / "realdata" / "cvusa_mini"


def smooth_image(rng, h: int, w: int) -> np.ndarray:
    small = rng.integers(0, 255, (h // 8 + 1, w // 8 + 1, 3), np.uint8)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def write_pairs(root: Path, n: int, aerial_hw, pano_hw, aerial_ext: str) -> Path:
    """A CVUSA-layout folder (val split) of n pairs of the given sizes."""
    rng = np.random.default_rng(0)
    for sub in ("bingmap/19", "streetview/panos", "splits"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    rows = []
    for i in range(1, n + 1):
        aerial, pano = f"bingmap/19/{i:07d}{aerial_ext}", f"streetview/panos/{i:07d}.jpg"
        quality = [cv2.IMWRITE_JPEG_QUALITY, 95] if aerial_ext == ".jpg" else []
        cv2.imwrite(str(root / aerial), smooth_image(rng, *aerial_hw), quality)
        cv2.imwrite(str(root / pano), smooth_image(rng, *pano_hw), [cv2.IMWRITE_JPEG_QUALITY, 95])
        rows.append(f"{aerial},{pano},unused.png\n")
    (root / "splits/val-19zl.csv").write_text("".join(rows))
    return root


def dataset_cfg(code: Path, overrides: list[str], root: Path, extra: dict):
    """The dataset keys (CrossViewDataConfig) that `python train.py <overrides>` composes, reading `root`."""
    from omegaconf import OmegaConf

    from geoloc.launch.hydra_hooks import compose_conf
    from geoloc.tasks.crossview.data_config import CrossViewDataConfig

    conf = code / "geoloc" / "conf"
    cfg = compose_conf("train", overrides, conf=conf if conf.is_dir() else code / "conf")  # an older checkout
    keys = {f.name for f in dataclasses.fields(CrossViewDataConfig)}
    section = {k: v for k, v in OmegaConf.to_container(cfg.dataset, resolve=False).items() if k in keys}
    section.update(name="cvusa", root=str(root), check_files="off")
    # reduced_decode and cache_decoded only where the measured code has them
    section.update({k: v for k, v in extra.items() if k in keys})
    return CrossViewDataConfig(**section)


def rate(fn, n: int) -> float:
    t0 = time.perf_counter()
    for i in range(n):
        fn(i)
    return n / (time.perf_counter() - t0)


def profile(pairs, n: int) -> dict[str, float]:
    """ms per pair of each stage of __getitem__, run stage by stage as it runs them."""
    from geoloc.data.io import read_rgb
    from geoloc.engine.sampling import item_rng
    from geoloc.tasks.crossview import transforms as T

    cfg, split, new = pairs.cfg, pairs.split, hasattr(T, "image_tensor")
    size = (lambda view: T.decode_size(cfg, view)) if new else (lambda view: None)
    stages = {"decode panorama": 0.0, "decode aerial": 0.0, "augment + align (IPT, resize)": 0.0,
              "tensor encoding in the worker": 0.0}
    for i in range(n):
        index = i % len(pairs)
        t0 = time.perf_counter()
        street = T.load_view(split.queries[index], split.query_view, *([size(split.query_view)] if new else []))
        t1 = time.perf_counter()
        aerial = read_rgb(split.references[index], *([size("aerial")] if new else []))
        t2 = time.perf_counter()
        rng = item_rng(0, (index, 0))
        query, reference = T.align(street, aerial, cfg, rng, split.query_view)
        t3 = time.perf_counter()
        if new:
            T.image_tensor(query), T.image_tensor(reference)
            if cfg.color_jitter > 0:
                T.jitter_draw(query, rng, cfg.color_jitter), T.jitter_draw(reference, rng, cfg.color_jitter)
        else:
            T.to_tensor(query, rng, cfg.color_jitter), T.to_tensor(reference, rng, cfg.color_jitter)
        t4 = time.perf_counter()
        for name, dt in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            stages[name] += dt * 1e3 / n
    return stages


def device_normalise_ms(pairs, batch: int = 16) -> float | None:
    """ms per pair of the batched normalisation (transforms.normalised) on this CPU; None where workers normalise."""
    from torch.utils.data import default_collate

    from geoloc.tasks.crossview import transforms as T

    if not hasattr(T, "normalised"):
        return None
    items = default_collate([pairs[(i % len(pairs), 0)] for i in range(batch)])
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        T.normalised(items)
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3 / batch


def run_case(name: str, code: Path, overrides: list[str], root: Path, extra: dict, pairs_per_round: int,
             rounds: int) -> dict:
    from geoloc.datasets.cvusa import cvusa
    from geoloc.tasks.crossview.datasets import CrossViewPairs

    cfg = dataset_cfg(code, overrides, root, extra)
    pairs = CrossViewPairs(cvusa(str(root), "val"), cfg, train=True)
    files = [(str(q), str(r)) for q, r in zip(pairs.split.queries, pairs.split.references)]
    n = len(files)
    bare = lambda i: (cv2.imread(files[i % n][0], cv2.IMREAD_COLOR), cv2.imread(files[i % n][1], cv2.IMREAD_COLOR))  # noqa: E731
    loader = lambda i: pairs[(i % n, i // n)]  # noqa: E731
    bare(0), loader(0)  # warm caches
    bare_rates, loader_rates = [], []
    for _ in range(rounds):  # alternating, so both see the same load on a shared machine
        bare_rates.append(rate(bare, pairs_per_round))
        loader_rates.append(rate(loader, pairs_per_round))
    item = pairs[(0, 0)]
    out = {"case": name, "bare": statistics.median(bare_rates), "loader": statistics.median(loader_rates),
           "profile": profile(pairs, pairs_per_round), "device_ms": device_normalise_ms(pairs),
           "shapes": f"{tuple(item['query'].shape)} {item['query'].dtype}".replace("torch.", ""),
           "reduced": getattr(cfg, "reduced_decode", None)}
    out["ratio"] = out["loader"] / out["bare"]
    return out


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--code", default=str(REPO), help="the checkout whose geoloc is measured (default: this one)")
    p.add_argument("--pairs", type=int, default=40, help="pairs per timed round")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--cases", nargs="+", default=["paper", "paper-area", "default", "default-reduced", "vigor",
                                                  "vigor-cpu", "vigor-cpu-cached"])
    args = p.parse_args(argv)
    code = Path(args.code).resolve()
    sys.path.insert(0, str(code))
    import torch

    import geoloc

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    tmp = Path(tempfile.mkdtemp(prefix="geoloc_bench_loader_"))
    paper_root = REALDATA if (REALDATA / "splits/val-19zl.csv").is_file() else write_pairs(
        tmp / "paper", 5, (750, 750), (224, 1232), ".jpg")
    default = ["dataset=cvusa", "dataset.joint_flip_rotate=true"]  # the synthetic dataset's keys, CVUSA's reader
    cases = {
        "paper": (["experiment=paper_cvusa"], lambda: paper_root, {}),
        "paper-area": (["experiment=paper_cvusa", "dataset.resize_interpolation=area"], lambda: paper_root, {}),
        "default": (default, lambda: write_pairs(tmp / "default", 8, (256, 256), (112, 616), ".jpg"),
                    {"reduced_decode": False}),
        "default-reduced": (default, lambda: tmp / "default", {"reduced_decode": True}),
        "vigor": (["dataset=vigor", "dataset.aerial_size=288"],
                  lambda: write_pairs(tmp / "vigor", 4, (640, 640), (1024, 2048), ".png"), {}),
        "vigor-cpu": (["experiment=vigor_cpu"],
                      lambda: write_pairs(tmp / "vigor_cpu", 8, (256, 256), (256, 512), ".png"),
                      {"cache_decoded": False}),
        "vigor-cpu-cached": (["experiment=vigor_cpu"], lambda: tmp / "vigor_cpu", {"cache_decoded": True}),
    }
    print(f"geoloc from {Path(geoloc.__file__).parent}; one core (torch threads {torch.get_num_threads()}, cv2 "
          f"threads {cv2.getNumThreads()}); paper-size files: {paper_root}; median of {args.rounds} rounds of "
          f"{args.pairs} pairs")
    results = []
    for name in args.cases:
        overrides, root, extra = cases[name]
        results.append(run_case(name, code, overrides, root(), extra, args.pairs, args.rounds))
        r = results[-1]
        stages = ", ".join(f"{k} {v:.2f}" for k, v in r["profile"].items())
        device = "" if r["device_ms"] is None else f"; batched normalise on this CPU {r['device_ms']:.2f} ms/pair"
        print(f"{name}: loader {r['loader']:.1f} pairs/s, bare cv2.imread {r['bare']:.1f} pairs/s, ratio "
              f"{r['ratio']:.2f} (item {r['shapes']}, reduced_decode {r['reduced']})\n  profile ms/pair: {stages}"
              f" (sum {sum(r['profile'].values()):.2f}){device}", flush=True)
    print("\n| case | loader pairs/s | bare decode pairs/s | ratio |\n|---|---|---|---|")
    for r in results:
        print(f"| {r['case']} | {r['loader']:.1f} | {r['bare']:.1f} | {r['ratio']:.2f} |")
    return results


if __name__ == "__main__":
    main()
