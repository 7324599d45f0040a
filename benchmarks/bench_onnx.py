"""ONNX export of the cross-view encoders: export time, file sizes, and onnxruntime against torch CPU latency per
image at batch 1 and 32, for the model `python train.py` builds (conf defaults; untrained: latency does not depend
on the weights). Overrides after `--` change the model, e.g. `-- experiment=paper_cvusa backbone.pretrained=false`.

    python benchmarks/bench_onnx.py [--threads 1] [--repeats 20] [-- KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1, help="torch and onnxruntime intra-op threads")
    parser.add_argument("--repeats", type=int, default=20, help="timed runs per batch size (median reported)")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 32])
    parser.add_argument("overrides", nargs="*", help="train.py config overrides for the model")
    args = parser.parse_args()

    import onnxruntime
    from geoloc.launch.hydra_hooks import compose_conf
    from geoloc.apps.export.onnx_export import export_encoders
    from geoloc.tasks.crossview import CrossViewEncoder
    from geoloc.tasks.crossview.crossview_config import parse_training
    from geoloc.tasks.crossview.crossview_run import build_task

    torch.set_num_threads(args.threads)
    cfg = compose_conf("train", [*args.overrides, "run_dir=."])
    torch.manual_seed(0)
    run = parse_training(cfg)
    task = build_task(run.model, run.components, run.trainer.max_epochs)
    views = {"task_info": {"query_view": {"train": "panorama", "val": "panorama"}}}  # what a CVUSA run records
    encoder = CrossViewEncoder(task, cfg, views, "untrained", torch.device("cpu"))
    model, data_cfg = encoder.model, encoder.data
    print(f"model: backbone={cfg.backbone.name} head={cfg.head.name} dim={cfg.model.dim} "
          f"alignment={data_cfg.alignment} aerial_size={data_cfg.aerial_size}; {args.threads} thread(s), "
          f"torch {torch.__version__}, onnxruntime {onnxruntime.__version__}")

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        started = time.perf_counter()
        spec = export_encoders(encoder, out)
        diff = max(spec[b]["checked_against_torch"]["max_abs_diff"] for b in ("query", "reference"))
        print(f"export (both branches, incl. the onnxruntime check): {time.perf_counter() - started:.1f} s, "
              f"opset {spec['opset']}, max abs difference from torch {diff:.2g}")
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = args.threads
        options.inter_op_num_threads = 1
        print("| branch | file MB | batch | torch ms/image | onnxruntime ms/image | torch / onnxruntime |")
        print("|---|---|---|---|---|---|")
        for branch in ("query", "reference"):
            entry = spec[branch]
            path = out / entry["file"]
            session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
            module = getattr(model, branch)
            for batch in args.batches:
                x = torch.randn(batch, *entry["input"]["shape"][1:])
                with torch.inference_mode():
                    torch_ms = per_image_ms(module, (x,), batch, args.repeats)
                feed = {entry["input"]["name"]: x.numpy()}
                ort_ms = per_image_ms(session.run, (None, feed), batch, args.repeats)
                print(f"| {branch} | {path.stat().st_size / 1e6:.1f} | {batch} | {torch_ms:.2f} | {ort_ms:.2f} | "
                      f"{torch_ms / ort_ms:.2f}x |")


def per_image_ms(run, run_args: tuple, batch: int, repeats: int) -> float:
    """Median over `repeats` timed calls of run(*run_args) (after 2 warm-up calls), in milliseconds per image."""
    for _ in range(2):
        run(*run_args)
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        run(*run_args)
        times.append(time.perf_counter() - started)
    return statistics.median(times) * 1e3 / batch


if __name__ == "__main__":
    main()
