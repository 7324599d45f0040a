"""DDP equivalences on CPU (gloo, 2 processes): training step, GMS queue, validation, and a torchrun smoke run.

Each spawned rank writes what it saw to a file; the test compares it with the same code run on one process.

The step test steps plain SGD, not the task's Adam. Adam's first update is lr * g / (|g| + eps): a gradient entry
that is zero up to rounding (1e-12 on one run, -1e-12 on the other, because 2 ranks sum in another order) moves
its weight by +lr on one run and -lr on the other, and step 2 then starts from different weights. SGD moves it by
lr * g, so rounding differences stay rounding differences. The optimizer is no part of what DDP must keep equal.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import pytest
import torch
import torch.multiprocessing as mp
from geoloc.config import checked
from geoloc.engine import Trainer, TrainerConfig, seed_everything
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine import distributed as dist
from geoloc.launch import hydra_hooks, run

from torch.utils.data import default_collate

from conftest import REPO, TINY, compose_evaluate, compose_train, write_cvusa
from helpers.crossview_runs import pairs_of, task_of

BATCH = 4  # the global batch; each of 2 ranks gets BATCH // 2
SGD_LR = 0.01  # moves the weights by up to ~0.04 a step: step 2 really runs on updated weights


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _join(rank: int, world: int, port: int) -> None:
    torch.set_num_threads(1)
    if world > 1:
        os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank),
                          WORLD_SIZE=str(world), LOCAL_RANK=str(rank))


def _setup(root, run_dir):
    cfg = compose_train([*TINY, f"dataset.root={root}", f"run_dir={run_dir}", "loss.queue_size=8"])
    seed_everything(0)  # same weights on every rank and in the 1-process run
    task = task_of(cfg)
    signal_init(task)
    trainer = Trainer(checked(cfg.trainer, TrainerConfig, "trainer"), run_dir)
    return cfg, task, trainer


def signal_init(task: torch.nn.Module) -> None:
    """He-normal conv/linear weights (torchvision's VGG init), drawn from the seeded global RNG.

    Under PyTorch's default init the 13 convolutions of the tiny test trunk shrink the signal to nothing: every
    descriptor equals the fc bias, the loss is ln 2, the first gradients are rounding noise below 3e-7 (under the
    comparison's atol, so that comparison could not fail) and the hardest negative is a tie.
    """
    for module in task.modules():
        if isinstance(module, (torch.nn.Conv2d, torch.nn.Linear)):
            torch.nn.init.kaiming_normal_(module.weight, nonlinearity="relu")


def _train_steps(rank, world, port, root, out_dir):
    """Two steps as Trainer._train_epoch does them: DDP(task)(batch, engine), backward, step, queue push."""
    _join(rank, world, port)
    cfg, task, trainer = _setup(root, out_dir / f"run{world}")
    model = task
    if dist.is_dist():
        model = torch.nn.parallel.DistributedDataParallel(task, broadcast_buffers=False)
    optimizer = torch.optim.SGD(task.parameters(), lr=SGD_LR)  # see the module docstring: not Adam
    dataset = pairs_of(cfg.dataset, "train", train=True)
    records = []
    for step in range(2):  # step 2's loss uses the queue filled by step 1
        full = default_collate([dataset[(i, 0)] for i in range(step * BATCH, (step + 1) * BATCH)])
        per_rank = BATCH // world
        batch = {k: v[rank * per_rank:(rank + 1) * per_rank] for k, v in full.items()}
        batch = task.on_after_batch_transfer(batch)  # the uint8 images the workers return, normalised
        out = model(batch, trainer.engine)
        trainer.engine.backward(out["loss"])
        grads = {n: p.grad.detach().clone() for n, p in task.named_parameters() if p.grad is not None}
        before = {n: p.detach().clone() for n, p in task.named_parameters()}
        trainer.engine.step(optimizer)
        task.on_train_batch_end(out)
        queue = {k: v.clone() for k, v in task.loss.queue.state_dict().items()}
        weights = {n: p.detach().clone() for n, p in task.named_parameters()}
        moved = torch.stack([(weights[n] - w).abs().max() for n, w in before.items()]).max()
        records.append({"loss": out["loss"].detach().clone(), "grads": grads, "queue": queue, "weights": weights,
                        "moved": moved})
    torch.save(records, out_dir / f"train_w{world}_r{rank}.pt")


def _validate(rank, world, port, root, out_dir):
    _join(rank, world, port)
    cfg, task, trainer = _setup(root, out_dir / f"run{world}")
    val_set = pairs_of(cfg.dataset, "val", train=False)
    loader = trainer.loader(val_set, 3, train=False)  # 8 items, batch 3: uneven shards and batches
    metrics = trainer.validate(task, loader)
    (out_dir / f"val_w{world}_r{rank}.json").write_text(json.dumps(metrics))


def _steps_then_validate(rank, world, port, root, out_dir):
    """Both records from one launch of each world size: a spawned rank spends most of its time importing."""
    _train_steps(rank, world, port, root, out_dir)
    _validate(rank, world, port, root, out_dir)  # in the process group the steps' trainer joined
    dist.cleanup()


def _run(fn, world, root, out_dir):
    if world == 1:
        fn(0, 1, 0, root, out_dir)
    else:
        mp.spawn(fn, args=(world, free_port(), root, out_dir), nprocs=world)


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """The folder where one process, then two, wrote what _train_steps and _validate saw."""
    out_dir = tmp_path_factory.mktemp("ddp")
    root = write_cvusa(out_dir / "cvusa", n_train=12, n_val=8)
    for world in (1, 2):
        _run(_steps_then_validate, world, root, out_dir)
    return out_dir


@pytest.mark.slow
def test_two_process_steps_equal_one_process_step(records):
    tmp_path = records
    single = torch.load(tmp_path / "train_w1_r0.pt", weights_only=True)
    for step, record in enumerate(single):  # the comparisons below can fail: gradients well above their atol
        grads = torch.cat([g.flatten() for g in record["grads"].values()]).abs()
        assert (grads > 1e-4).float().mean() > 0.3, f"step {step}: gradients vanish, the comparison proves nothing"
    assert single[0]["moved"] > 1e-3  # step 2 runs on weights that step 1 moved
    for rank in (0, 1):
        ddp = torch.load(tmp_path / f"train_w2_r{rank}.pt", weights_only=True)
        for step, (a, b) in enumerate(zip(single, ddp)):
            assert b["loss"].item() == pytest.approx(a["loss"].item(), rel=1e-5, abs=1e-6), (rank, step)
            assert a["grads"].keys() == b["grads"].keys()
            for name, grad in a["grads"].items():
                # 2 ranks sum in another order: entries near zero in a tensor of gradients near 0.1 differ by
                # float32 rounding of that scale (~1e-6), so the absolute tolerance follows the tensor's scale
                scale = float(grad.abs().max())
                torch.testing.assert_close(b["grads"][name], grad, rtol=1e-4, atol=max(1e-6, 1e-5 * scale),
                                           msg=lambda m: f"rank {rank} step {step} {name}: {m}")
            for name, weight in a["weights"].items():  # the weights after the step, which step 2 starts from
                torch.testing.assert_close(b["weights"][name], weight, rtol=1e-5, atol=1e-7,
                                           msg=lambda m: f"rank {rank} step {step} weight {name}: {m}")
            # the queue is gathered before the push: identical on every rank and to the 1-process queue
            assert torch.equal(b["queue"]["ids"], a["queue"]["ids"])
            assert torch.equal(b["queue"]["ptr"], a["queue"]["ptr"])
            torch.testing.assert_close(b["queue"]["descriptors"], a["queue"]["descriptors"], rtol=1e-5, atol=1e-6)
        assert int((ddp[0]["queue"]["ids"] >= 0).sum()) == BATCH  # one hardest negative per global query
    r0 = torch.load(tmp_path / "train_w2_r0.pt", weights_only=True)
    r1 = torch.load(tmp_path / "train_w2_r1.pt", weights_only=True)
    for a, b in zip(r0, r1):
        assert all(torch.equal(a["queue"][k], b["queue"][k]) for k in a["queue"])


@pytest.mark.slow
def test_two_process_validation_recall_equals_one_process(records):
    tmp_path = records
    single = json.loads((tmp_path / "val_w1_r0.json").read_text())
    assert set(single) >= {"R@1", "R@5", "R@10", "R@1%"}
    assert single["reference_spread"] > 0.1  # distinct descriptors: the ranks are not ties decided by rounding
    for rank in (0, 1):
        ddp = json.loads((tmp_path / f"val_w2_r{rank}.json").read_text())
        assert ddp.keys() == single.keys()
        for key, value in single.items():
            # recall counts ranks: exact. The spread sums float32 stds of descriptors that other batch
            # compositions computed, so it agrees to float32 rounding only.
            tolerance = {"rel": 1e-6} if key == "reference_spread" else {"abs": 1e-9}
            assert ddp[key] == pytest.approx(value, **tolerance), (rank, key)


@pytest.mark.slow
def test_torchrun_smoke_writes_one_run_dir_that_single_process_evaluate_loads(tiny_cvusa, tmp_path):
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--master_addr=127.0.0.1",
           f"--master_port={free_port()}", str(REPO / "train.py"), *TINY, f"dataset.root={tiny_cvusa}",
           "trainer.max_epochs=1"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    ckpts = sorted(tmp_path.glob("outputs/**/last.pt"))
    assert len(ckpts) == 1, ckpts  # one run dir for both ranks
    run_dir = ckpts[0].parent
    assert [p for p in tmp_path.glob("outputs/*/*/*")] == [run_dir]  # rank 1 made no Hydra dir of its own
    assert not list(run_dir.glob(".last.pt.*.tmp"))
    lines = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    val = [r for r in lines if "val/R@1" in r]
    assert len(val) == 1  # rank 0 alone logs

    state = ckpt_io.load(ckpts[0])
    assert not any(k.startswith("module.") for k in state["task"])  # saved unwrapped
    metrics = run.evaluate(compose_evaluate([f"ckpt={ckpts[0]}", "progress=false", "device=cpu",
                                             f"run_dir={tmp_path / 'eval'}"]))
    for key in ("R@1", "R@5", "R@10", "R@1%"):
        assert metrics[key] == pytest.approx(val[0][f"val/{key}"], abs=1e-9)


def test_slurm_tasks_get_a_rendezvous_address_and_port(monkeypatch):
    for name in ("RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("SLURM_PROCID", "3")
    monkeypatch.setenv("SLURM_JOB_ID", "123456")
    monkeypatch.setenv("SLURM_JOB_NUM_NODES", "2")
    monkeypatch.setenv("SLURM_JOB_NODELIST", "gpu[07-08]")
    monkeypatch.setattr(dist.subprocess, "run", _no_scontrol)
    dist.slurm_master_env()
    assert os.environ["MASTER_ADDR"] == "gpu07"
    assert os.environ["MASTER_PORT"] == str(20000 + 123456 % 20000)
    monkeypatch.setenv("MASTER_ADDR", "10.0.0.1")  # an address the job exported wins
    dist.slurm_master_env()
    assert os.environ["MASTER_ADDR"] == "10.0.0.1"


def _no_scontrol(*args, **kwargs):
    raise FileNotFoundError("scontrol")


def test_ranks_above_zero_get_a_throwaway_hydra_dir(monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    assert hydra_hooks.hydra_overrides_for_rank() == []
    monkeypatch.setenv("RANK", "1")
    assert "hydra.output_subdir=null" in hydra_hooks.hydra_overrides_for_rank()
