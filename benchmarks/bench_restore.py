"""What restoring a cross-view checkpoint costs: the task built under unfilled_init (what evaluate.py, the apps and
`geoloc bench` do) against the same build drawing every random initial weight first, both then given the same
weights by the strict load.

Each configuration's task is built once to make a state to load. Then the two ways alternate (unfilled, drawn,
unfilled, drawn...) so both see the same load; the medians, the fastest rounds and their ratios are printed, and
every restored state is checked to equal the saved one exactly.

    OMP_NUM_THREADS=1 python benchmarks/bench_restore.py                    # the default recipe and the paper's
    OMP_NUM_THREADS=1 python benchmarks/bench_restore.py --configs default --rounds 7
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from geoloc.launch.hydra_hooks import compose_conf  # noqa: E402
from geoloc.tasks.crossview.crossview_config import parse_components  # noqa: E402
from geoloc.tasks.crossview.crossview_run import build_task, loaded_task, with_weights  # noqa: E402

CONFIGS = {  # the default recipe (python train.py) and the paper's network (two full-width VGG16s, D 4,096)
    "default": [],
    "paper": ["experiment=paper_cvusa", "backbone.pretrained=false", "dataset.root=/unused"],
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {args.rounds} rounds each")
    print("| network | unfilled median (s) | drawn median (s) | drawn / unfilled (median) | (fastest) |")
    print("|---|---|---|---|---|")
    for name in args.configs:
        stored = compose_conf("train", CONFIGS[name])
        model, components, epochs = stored.model, parse_components(stored), stored.trainer.max_epochs
        saved = build_task(model, components, epochs).state_dict()
        state = {"task": saved, "config": "{}"}
        times = {"unfilled": [], "drawn": []}
        for _ in range(args.rounds):
            for way in times:
                start = time.perf_counter()
                if way == "unfilled":
                    task = loaded_task(model, components, stored, state, "bench")
                else:
                    task = with_weights(build_task(model, components, epochs), state, "bench")
                times[way].append(time.perf_counter() - start)
                restored = task.state_dict()
                assert all(torch.equal(restored[k], v) for k, v in saved.items()), f"{name}: {way} differs"
        med = {way: statistics.median(t) for way, t in times.items()}
        low = {way: min(t) for way, t in times.items()}
        print(f"| {name} | {med['unfilled']:.2f} | {med['drawn']:.2f} | {med['drawn'] / med['unfilled']:.1f}x | "
              f"{low['drawn'] / low['unfilled']:.1f}x |")


if __name__ == "__main__":
    main()
