"""Backbone cost on a CPU: parameters and forward (and forward + backward) time of timm backbones against geoloc's
default VGG16-BN trunk at width 0.125, to pick a CPU-sized backbone of comparable cost (docs/backbones.md).

    python benchmarks/bench_backbones.py [--threads 2] [--batch 32] [--size 64] [--repeats 5]
"""
import argparse
import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from geoloc.models.timm_backbone import timm_backbone
from geoloc.models.vgg import VGG16Trunk

CANDIDATES = {
    "VGG16-BN w0.125 (default trunk)": lambda: VGG16Trunk(0.125, False, None, True),
    "convnext dims 16-128 depths 1,1,2,1": lambda: timm_backbone(
        "convnext_tiny", model_args=dict(dims=[16, 32, 64, 128], depths=[1, 1, 2, 1])),
    "convnext dims 24-192 depths 1,1,3,1": lambda: timm_backbone(
        "convnext_tiny", model_args=dict(dims=[24, 48, 96, 192], depths=[1, 1, 3, 1])),
    "convnext dims 32-256 depths 1,1,3,1": lambda: timm_backbone(
        "convnext_tiny", model_args=dict(dims=[32, 64, 128, 256], depths=[1, 1, 3, 1])),
    "convnext dims 24-192 depths 2,2,6,2": lambda: timm_backbone(
        "convnext_tiny", model_args=dict(dims=[24, 48, 96, 192], depths=[2, 2, 6, 2])),
    "convnext dims 32-256 depths 2,2,6,2": lambda: timm_backbone(
        "convnext_tiny", model_args=dict(dims=[32, 64, 128, 256], depths=[2, 2, 6, 2])),
    "same, out_indices 0,1,2 (strides 4-16)": lambda: timm_backbone(
        "convnext_tiny", out_indices=[0, 1, 2], model_args=dict(dims=[32, 64, 128, 256], depths=[2, 2, 6, 2])),
    "convnext_atto (has ImageNet weights)": lambda: timm_backbone("convnext_atto"),
    "deit embed 96 depth 6 heads 3 (img 64)": lambda: timm_backbone(
        "deit_tiny_patch16_224", model_args=dict(img_size=64, embed_dim=96, depth=6, num_heads=3)),
}


def forward_gflops(net, x):
    """Multiply-adds x 2 of one forward, counted by torch (contention-free, unlike the times)."""
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        net(x)
    return counter.get_total_flops() / 1e9


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    x = torch.randn(args.batch, 3, args.size, args.size)
    nets = {}
    for name, build in CANDIDATES.items():
        torch.manual_seed(0)
        nets[name] = build().train()

    def forward(net):
        with torch.no_grad():
            net(x)

    def forward_backward(net):
        sum(m.mean() for m in net(x)).backward()

    # rounds over all backbones in turn, keeping each one's best time: on a shared machine the other jobs' load
    # then falls on every backbone alike, and the best is the least disturbed run
    best = {name: [float("inf"), float("inf")] for name in nets}
    for _ in range(args.repeats + 1):  # the first round warms up (allocator, oneDNN kernels) and counts too
        for name, net in nets.items():
            for k, step in enumerate((forward, forward_backward)):
                t = time.perf_counter()
                step(net)
                best[name][k] = min(best[name][k], time.perf_counter() - t)
    print(f"batch {args.batch}, {args.size}x{args.size}, {args.threads} threads, best of {args.repeats + 1} rounds")
    print(f"{'backbone':42s} {'params':>8s} {'GFLOPs':>7s} {'fwd ms':>7s} {'fwd+bwd ms':>10s}  maps (C, h, w)")
    base = None
    for name, net in nets.items():
        params = sum(p.numel() for p in net.parameters()) / 1e6
        gflops = forward_gflops(net, x)
        base = base or best[name][0]
        with torch.no_grad():
            shapes = [tuple(m.shape[1:]) for m in net(x)]
        print(f"{name:42s} {params:7.3f}M {gflops:7.2f} {1000 * best[name][0]:7.0f} {1000 * best[name][1]:10.0f}  "
              f"{shapes}  fwd {best[name][0] / base:.2f}x")


if __name__ == "__main__":
    main()
