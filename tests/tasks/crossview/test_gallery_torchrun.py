"""`torchrun --nproc_per_node=2 evaluate.py ... gallery.save=DIR` (2 CPU processes, gloo) writes the gallery one
process writes: the same rows in the same order, the same descriptors to float tolerance, the same recall; and a
gallery built by shard jobs through evaluate.py and merged scores as the one-job gallery."""

from __future__ import annotations

import importlib.util
import json
import os
import socket
import subprocess
import sys

import pytest
import torch
from geoloc.cli import main as geoloc
from geoloc.eval import GalleryIndex
from geoloc.launch import run

from conftest import REPO, TINY, compose_evaluate, compose_train, write_cvusa

RECALL = ("R@1", "R@5", "R@10", "R@1%")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def evaluate(tmp_path, ckpt, name, *extra):
    return run.evaluate(compose_evaluate([f"ckpt={ckpt}", "progress=false", "device=cpu",
                                          f"run_dir={tmp_path / name}", *extra]))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """One epoch of the tiny network on tiny CVUSA pairs, trained once for both tests: its best.pt (the dataset's
    root is stored in the checkpoint's config, so evaluate.py finds it)."""
    folder = tmp_path_factory.mktemp("trained")
    root = write_cvusa(folder / "cvusa", n_train=12, n_val=8)
    run.train(compose_train([*TINY, f"dataset.root={root}", f"run_dir={folder / 'run'}", "trainer.max_epochs=1"]))
    return folder / "run" / "best.pt"


@pytest.mark.slow
def test_a_torchrun_gallery_equals_the_one_process_gallery(trained, tmp_path):
    ckpt = trained
    single = evaluate(tmp_path, ckpt, "eval1", f"gallery.save={tmp_path / 'one'}")
    out = tmp_path / "metrics.json"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--master_addr=127.0.0.1",
           f"--master_port={free_port()}", str(REPO / "evaluate.py"), f"ckpt={ckpt}", "device=cpu", "progress=false",
           f"gallery.save={tmp_path / 'two'}", f"metrics_out={out}", f"hydra.run.dir={tmp_path / 'eval2'}"]
    proc = subprocess.run(cmd, cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    ddp = json.loads(out.read_text())
    for key in RECALL:
        assert ddp[key] == single[key], key
    one, two = (tmp_path / "one", tmp_path / "two")
    for name in ("references.jsonl", "queries.jsonl"):
        assert (two / name).read_bytes() == (one / name).read_bytes(), name  # the same rows in the same order
    a, b = (GalleryIndex.load(d / "gallery.pt").vectors() for d in (one, two))
    assert a.shape == b.shape == (8, 16)
    torch.testing.assert_close(b, a, rtol=0, atol=1e-6)

    # three shard jobs through evaluate.py, merged with `geoloc gallery merge`, score as the one-job gallery
    shards = [tmp_path / f"shard{i}" for i in range(3)]
    for i, folder in enumerate(shards):
        evaluate(tmp_path, ckpt, f"eval_shard{i}", f"gallery.save={folder}", "gallery.num_shards=3",
                 f"gallery.shard_index={i}")
    assert [json.loads((f / "gallery.json").read_text())["num_references"] for f in shards] == [2, 3, 3]
    assert geoloc(["gallery", "merge", *map(str, shards), f"out={tmp_path / 'merged'}"]) == 0
    merged = evaluate(tmp_path, ckpt, "eval_merged", f"gallery.load={tmp_path / 'merged'}")
    for key in RECALL:
        assert merged[key] == single[key], key
    torch.testing.assert_close(GalleryIndex.load(tmp_path / "merged" / "gallery.pt").vectors(), a, rtol=0, atol=1e-6)


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("hydra_plugins.hydra_submitit_launcher") is None,
                    reason="hydra-submitit-launcher is not installed")
def test_shard_jobs_through_the_submitit_launcher_merge_into_the_one_job_gallery(trained, tmp_path):
    """docs/distributed.md's step 2 as written, with submitit's local executor in place of SLURM's: one Hydra sweep
    over gallery.shard_index, each job its own process, then one merge."""
    ckpt = trained
    single = evaluate(tmp_path, ckpt, "eval1", f"gallery.save={tmp_path / 'one'}")
    shards = tmp_path / "shards"
    cmd = [sys.executable, str(REPO / "evaluate.py"), "-m", "hydra/launcher=submitit_local", f"ckpt={ckpt}",
           "device=cpu", "progress=false", "gallery.num_shards=3", "gallery.shard_index=range(0,3)",
           f"gallery.save={shards}/" + "${gallery.shard_index}", f"hydra.sweep.dir={tmp_path / 'sweep'}",
           "hydra.launcher.timeout_min=5", "hydra.launcher.cpus_per_task=1"]
    proc = subprocess.run(cmd, cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    folders = [shards / str(i) for i in range(3)]
    assert [json.loads((f / "gallery.json").read_text())["part"]["shard_index"] for f in folders] == [0, 1, 2]
    assert geoloc(["gallery", "merge", *map(str, folders), f"out={tmp_path / 'merged'}"]) == 0
    merged = evaluate(tmp_path, ckpt, "eval_merged", f"gallery.load={tmp_path / 'merged'}")
    for key in RECALL:
        assert merged[key] == single[key], key
    one = GalleryIndex.load(tmp_path / "one" / "gallery.pt").vectors()
    torch.testing.assert_close(GalleryIndex.load(tmp_path / "merged" / "gallery.pt").vectors(), one, rtol=0, atol=1e-6)
