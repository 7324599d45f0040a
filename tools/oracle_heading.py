"""Is the positive distinguishable without training? Scores the synthetic default world's validation pairs with
fixed, untrained similarities, heading known and searched, at FoV 360 / 180 / 90 (docs/heading.md, "Diagnosis").

    PYTHONPATH=. python tools/oracle_heading.py [split] [n]      # default: val 300

Each query is the IPT (64 px) of its view placed on the 360° canvas, as validation makes it
(CrossViewPairs with heading_search, 36 candidate headings); each reference its 64 px aerial tile. Descriptors:
`pixels`, the 16x16 average-pooled image, and `randconv`, the 8x8 pooled maps of a fixed random two-layer CNN
(seed 0), each centred and L2-normalised. "known" takes the candidate nearest the true heading; "searched"
scores max over candidates with geoloc's scorer (heading_metrics).
"""

import sys

import torch
import torch.nn.functional as F

import geoloc.datasets  # noqa: F401  (registers the readers)
from geoloc import registry
from geoloc.data.relevance import Relevance
from geoloc.eval.retrieval_metrics import scored_metrics
from geoloc.tasks.crossview.data_config import CrossViewDataConfig
from geoloc.tasks.crossview.datasets import CrossViewPairs
from geoloc.tasks.crossview.heading import heading_metrics
from geoloc.tasks.crossview.transforms import normalise

STEPS = 36


def random_features() -> torch.nn.Module:
    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Conv2d(3, 32, 5, padding=2), torch.nn.ReLU(), torch.nn.AvgPool2d(2),
                               torch.nn.Conv2d(32, 64, 5, padding=2), torch.nn.ReLU(), torch.nn.AvgPool2d(2))


def descriptors(x: torch.Tensor, kind: str, conv: torch.nn.Module) -> torch.Tensor:
    """x: (N, 3, H, W) uint8 images as the data sets give them (normalised here as the task does) or float."""
    if x.dtype == torch.uint8:
        x = normalise(x)
    with torch.no_grad():
        y = F.adaptive_avg_pool2d(x if kind == "pixels" else conv(x), 16 if kind == "pixels" else 8).flatten(1)
    return F.normalize(y - y.mean(1, keepdim=True), dim=1)


def main(split_name: str = "val", n: int = 300) -> None:
    split = registry.build("dataset", {"name": "synthetic"}, root=None, split=split_name)
    conv = random_features()
    print(f"{n} {split_name} places, chance R@1 {100 / n:.2f}%")
    for fov in (360.0, 180.0, 90.0):
        cfg = CrossViewDataConfig(aerial_size=64, pano_size=[32, 176], fov=fov, random_heading=True,
                                  heading_steps=STEPS)
        pairs = CrossViewPairs(split, cfg, train=False, heading_search=True)
        items = [pairs[i] for i in range(n)]
        candidates = torch.stack([it["query"] for it in items])  # Q×K×3×H×W
        references = torch.stack([it["reference"] for it in items])
        heading = torch.tensor([it["heading"] for it in items])
        nearest = torch.round(heading / (360.0 / STEPS)).long() % STEPS
        for kind in ("pixels", "randconv"):
            q = descriptors(candidates.flatten(0, 1), kind, conv).unflatten(0, candidates.shape[:2])
            r = descriptors(references, kind, conv)
            known = scored_metrics(q[torch.arange(n), nearest], r, Relevance.one_to_one(n, n))
            searched = heading_metrics(q, r, heading)
            print(f"| {fov:.0f} | {kind} | {100 * known['R@1']:.2f} | {100 * known['R@10']:.2f} | "
                  f"{100 * searched['R@1']:.2f} | {100 * searched['R@10']:.2f} | "
                  f"{searched['heading_median_deg']:.1f} | {100 * searched['heading_within_10deg']:.0f} |", flush=True)


if __name__ == "__main__":
    torch.set_num_threads(1)
    main(*(sys.argv[1:2] or ["val"]), *([int(sys.argv[2])] if len(sys.argv) > 2 else []))
