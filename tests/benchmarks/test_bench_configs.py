"""The benchmarks compose train.py's config in a process of their own, where no test's conftest has stored the
schema nodes that geoloc/conf/ extends. Each composes it through `compose_conf`, which stores them: bench_train.py once
composed it bare and failed at its first line on a GPU machine ("Could not load 'schema/views/single'")."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"

COMPOSE = {  # benchmark module -> (code composing its config, the value it prints)
    "bench_train": ("args = argparse.Namespace(batch=3, device='cpu', workers=0, precision='32', channels_last=False, "
                    "compile=False); cfg = m.config(args, Path('/nowhere'), Path('/nowhere/run')); "
                    "print(cfg.dataset.batch_size, cfg.model.dim)", "3 4096"),
    "bench_overhead": ("cfg = m.train_config(argparse.Namespace(epochs=2), Path('/nowhere/run')); "
                       "print(cfg.trainer.max_epochs, cfg.sampler.name)", "2 shuffle"),
}


@pytest.mark.parametrize("module", sorted(COMPOSE))
def test_benchmark_composes_its_config_in_a_fresh_process(module):
    code, expected = COMPOSE[module]
    script = f"import argparse, importlib; from pathlib import Path; m = importlib.import_module('{module}'); {code}"
    done = subprocess.run([sys.executable, "-c", script], cwd=BENCHMARKS, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split("\n")[-2].strip() == expected
