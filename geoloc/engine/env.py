"""The software and thread count a run computed on, so that a figure can be traced to its environment.

Two runs give bit-identical numbers only with the same versions *and* the same thread count: torch's CPU kernels
split reductions (convolution, matmul, sums) over threads, and the order of a float sum changes its last bits.
The trainer prints `describe(environment())` at fit start and keeps the dict in env.json and in checkpoints;
.ci/run prints the same line before the tests.
"""

from __future__ import annotations

import json
import os
import platform
from importlib import metadata
from pathlib import Path
from typing import Any

import torch

import geoloc
from geoloc.engine import distributed as dist

#: name shown -> the distributions that provide it (the first one installed counts)
PACKAGES = {
    "torch": ("torch",),
    "torchvision": ("torchvision",),
    "numpy": ("numpy",),
    "opencv": ("opencv-python-headless", "opencv-python", "opencv-contrib-python-headless", "opencv-contrib-python"),
    "faiss": ("faiss-cpu", "faiss-gpu", "faiss"),
    "scipy": ("scipy",),
    "hydra-core": ("hydra-core",),
}


def installed_version(distributions: tuple[str, ...]) -> str | None:
    """Version of the first installed distribution of `distributions`; None when none is installed."""
    for name in distributions:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return None


def environment() -> dict[str, Any]:
    """{python, geoloc, each of PACKAGES (None if absent), threads, OMP_NUM_THREADS, cuda, gpu, platform}."""
    env: dict[str, Any] = {"python": platform.python_version(), "geoloc": geoloc.__version__}
    env.update({shown: installed_version(dists) for shown, dists in PACKAGES.items()})
    # torch.__version__ keeps the build tag (2.15.0+cu132) that the wheel metadata leaves out; str() because it is
    # a str subclass that torch.load(weights_only=True) refuses
    env["torch"] = str(torch.__version__)
    env["threads"] = torch.get_num_threads()  # what the kernels use; OMP_NUM_THREADS only sets its default
    env["OMP_NUM_THREADS"] = os.environ.get("OMP_NUM_THREADS")
    env["cuda"] = torch.version.cuda
    env["gpu"] = torch.cuda.get_device_name() if torch.cuda.is_available() else None
    env["platform"] = platform.platform()
    return env


def describe(env: dict[str, Any]) -> str:
    """One line: `python 3.11.7 | torch 2.15.0 | ... | threads 2`, absent packages shown as `-`."""
    shown = [f"{key} {'-' if value is None else value}" for key, value in env.items() if key != "platform"]
    return "environment: " + " | ".join(shown)


def record_environment(run_dir: str | Path) -> dict[str, Any]:
    """At fit start: rank 0 prints `describe(...)` and writes RUN_DIR/env.json. Every rank returns the dict."""
    env = environment()
    if dist.is_main():
        print(describe(env), flush=True)
        Path(run_dir).mkdir(parents=True, exist_ok=True)
        (Path(run_dir) / "env.json").write_text(json.dumps(env, indent=1) + "\n")
    return env
