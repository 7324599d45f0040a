"""MMDIP speed figures: SPM coding per pyramid level, BoW + SPM coding, and per-stage latency per query.

Paper (TITAN Xp, 512 x 512): segmentation 20 ms, translation 15 ms, coding + retrieval 22 ms per query; its CPU
needed about 157 ms more for SPM at L = 6 than at L = 0. Targets on one core here: SPM at L = 6 of a 512 x 512 map
<= 5 ms; BoW + SPM coding at L = 2 <= 22 ms. Runs on one thread (torch and OpenCV); a GPU is timed too when there.

    OMP_NUM_THREADS=1 python benchmarks/bench_mmdip.py [--root DYNAMIC_LAYOUT_DIR] [--gallery 1000] [--repeat 20]

Images: the first views of --root (a `dynamic` layout), else a handful of 512 x 512 views generated into a temp
folder. Networks are random-initialised at the paper's sizes (ERFNet, pix2pix U-Net 256 with 8 downs) since
speed does not depend on the weights.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from geoloc.tasks.mmdip.datasets import DynamicDataset  # noqa: E402
from geoloc.models.erfnet import ERFNet  # noqa: E402
from geoloc.models.unet import UNet  # noqa: E402
from geoloc.tasks.mmdip.networks import generator_input  # noqa: E402
from geoloc.vpr import ORBExtractor, Vocabulary, fused_similarity, spm_encode  # noqa: E402


def median_ms(fn, repeat: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def load_views(root: str | None, n: int) -> tuple[np.ndarray, np.ndarray]:
    if root is None:
        from geoloc.synthetic import generate

        root = tempfile.mkdtemp(prefix="bench_mmdip_")
        print(f"generating {n} places of 512 x 512 views into {root} ...")
        generate("dynamic", root, n, 1, seed=0, preset="dynamic_small", view_size=512, progress=False)
    ds = DynamicDataset(root, "train", image_size=(512, 512), check="off")
    items = [ds[i] for i in range(min(2 * n, len(ds)))]
    images = np.stack([(it["static"].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for it in items])
    labels = np.stack([it["label"].numpy().astype(np.uint8) for it in items])
    return images, labels


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", default=None)
    p.add_argument("--places", type=int, default=6)
    p.add_argument("--gallery", type=int, default=1000, help="references in the retrieval timing")
    p.add_argument("--vocab", type=int, default=1000)
    p.add_argument("--repeat", type=int, default=20)
    p.add_argument("--net-repeat", type=int, default=3)
    args = p.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    images, labels = load_views(args.root, args.places)
    seg = labels[0].astype(np.int64)
    print(f"\nsingle thread (torch {torch.get_num_threads()}, cv2 {cv2.getNumThreads()}), 512 x 512\n")

    print("| SPM levels L | code length | ms per map |\n|---|---|---|")
    spm_ms = {}
    for levels in range(7):
        spm_ms[levels] = median_ms(lambda: spm_encode(seg, 8, levels), args.repeat)
        print(f"| {levels} | {len(spm_encode(seg, 8, levels))} | {spm_ms[levels]:.2f} |")
    print(f"SPM L=6 - L=0: {spm_ms[6] - spm_ms[0]:.2f} ms (paper's CPU: about 157 ms); target L=6 <= 5 ms: "
          f"{'met' if spm_ms[6] <= 5 else 'NOT met'}")

    orb = ORBExtractor(500)
    vocab = Vocabulary.fit([orb(img) for img in images], args.vocab, iters=5)
    img = images[-1]
    orb_ms = median_ms(lambda: orb(img), args.repeat)
    desc = orb(img)
    assign_ms = median_ms(lambda: vocab.encode(desc), args.repeat)
    spm2_ms = median_ms(lambda: spm_encode(seg, 8, 2), args.repeat)
    coding_ms = median_ms(lambda: (vocab.encode(orb(img)), spm_encode(seg, 8, 2)), args.repeat)
    print(f"\nBoW + SPM coding at L=2 ({len(desc)} ORB features, {vocab.size} words): ORB {orb_ms:.2f} ms, "
          f"BoW assignment + tf-idf {assign_ms:.2f} ms, SPM {spm2_ms:.2f} ms; total {coding_ms:.2f} ms per query "
          f"(target <= 22 ms: {'met' if coding_ms <= 22 else 'NOT met'})")

    rng = np.random.default_rng(0)
    g_bow = rng.random((args.gallery, vocab.size), dtype=np.float32)
    g_spm = rng.random((args.gallery, len(spm_encode(seg, 8, 2))), dtype=np.float32)
    q_bow, q_spm = vocab.encode(desc)[None], spm_encode(seg, 8, 2)[None]
    retrieval_ms = median_ms(lambda: np.argsort(-fused_similarity(q_bow, q_spm, g_bow, g_spm)[0])[:10],
                             args.repeat)

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print("\nper-stage latency per query (ms; segmentation = ERFNet, translation = pix2pix U-Net 256 with 8 downs,"
          f" retrieval = eq. 5 against {args.gallery} references)")
    print("| device | segmentation | translation | coding (BoW + SPM, L=2) | retrieval | total |\n|---|---|---|---|---|---|")
    for device in devices:
        seg_net, gen = ERFNet(8).eval().to(device), UNet(16, 3, num_downs=8, ngf=64).eval().to(device)
        x = torch.from_numpy(img).permute(2, 0, 1)[None].float().div(255).to(device)

        def sync():
            if device == "cuda":
                torch.cuda.synchronize()

        with torch.no_grad():
            logits = seg_net(x)

            def run_seg():
                seg_net(x)
                sync()

            def run_gen():
                gen(generator_input("ssggnet", x, logits, None))
                sync()

            repeat = args.net_repeat if device == "cpu" else 20
            s_ms, g_ms = median_ms(run_seg, repeat), median_ms(run_gen, repeat)
        total = s_ms + g_ms + coding_ms + retrieval_ms
        print(f"| {device} | {s_ms:.1f} | {g_ms:.1f} | {coding_ms:.1f} | {retrieval_ms:.2f} | {total:.1f} |")
    print("(coding and retrieval run on the CPU in both rows)")


if __name__ == "__main__":
    main()
