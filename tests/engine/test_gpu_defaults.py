"""The engine's GPU-first defaults and its checkpoint writes: trainer.channels_last/compile "auto" (on for CUDA, off
on the CPU), a compile that fails falling back to eager, one serialisation per epoch (best.pt a link to last.pt),
written on a background thread from a copy of the state taken when the epoch ended."""

from __future__ import annotations

import os
import time

import pytest
import torch
from geoloc.config import ConfigError, checked
from geoloc.engine import Trainer, TrainerConfig, seed_everything
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine.device import amp_dtype, on_for_cuda
from geoloc.launch.hydra_hooks import compose_conf

from test_trainer import NoisyLine, NoisyPoints, config
from toy_task import Points, ScriptedRecall


def test_auto_is_on_for_cuda_and_off_on_the_cpu():
    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    assert on_for_cuda("auto", cuda) and not on_for_cuda("auto", cpu)
    assert on_for_cuda(True, cpu) and not on_for_cuda(False, cuda)  # a stored true/false is kept
    trainer = Trainer(config(), "unused")
    assert TrainerConfig().channels_last == TrainerConfig().compile == "auto"
    assert trainer.channels_last is False and trainer.compile is False
    assert amp_dtype("bf16", cpu) is None and amp_dtype("32", cuda) is None
    assert amp_dtype("bf16", cuda) == torch.bfloat16 and amp_dtype("16", cuda) == torch.float16


def test_the_paper_recipe_and_the_default_run_leave_both_switches_on_auto():
    for overrides in ([], ["experiment=paper_cvusa"]):
        trainer = checked(compose_conf("train", overrides).trainer, TrainerConfig, "trainer")
        assert (trainer.channels_last, trainer.compile) == ("auto", "auto"), overrides


@pytest.mark.parametrize("value", ["yes", 1.5, "cuda"])
def test_a_switch_takes_true_false_or_auto_only(value):
    with pytest.raises(ConfigError, match="trainer.compile must be true, false or auto"):
        checked({"compile": value}, TrainerConfig, "trainer")


class FailingCompile:
    """torch.compile as it behaves where compiling fails (an inductor without a C compiler): what it returns fails
    when called. A module gets a module back (as torch's OptimizedModule), a function a callable (Module.compile)."""

    calls = 0

    def __new__(cls, fn, *args, **kwargs):
        if isinstance(fn, torch.nn.Module):
            return FailingModule(fn)
        return super().__new__(cls)

    def __init__(self, fn, *args, **kwargs):
        self.fn = fn

    def __call__(self, *args, **kwargs):
        FailingCompile.calls += 1
        raise RuntimeError("BackendCompilerFailed: backend='inductor' raised:\nno C compiler found")


class FailingModule(torch.nn.Module):
    def __init__(self, module):
        super().__init__()
        self.module = module  # a child: train()/eval() reach it, as with OptimizedModule

    def forward(self, *args, **kwargs):
        return FailingCompile.__call__(self)


def test_a_compile_that_fails_falls_back_to_eager_with_one_line(tmp_path, monkeypatch, capsys):
    eager, _ = fit_line(tmp_path / "eager")
    monkeypatch.setattr(torch, "compile", FailingCompile)
    FailingCompile.calls = 0
    compiled, _ = fit_line(tmp_path / "compiled", compile=True)
    assert FailingCompile.calls == 1  # tried once, on the first step; eager from then on
    out = capsys.readouterr().out
    assert out.count("torch.compile failed on the first step (RuntimeError: BackendCompilerFailed") == 1
    for (name, a), (_, b) in zip(eager.state_dict().items(), compiled.state_dict().items()):
        assert torch.equal(a, b), name  # the failed attempt left no trace in the weights


def test_an_error_of_the_step_itself_is_raised_not_hidden_by_the_fallback(tmp_path, monkeypatch):
    monkeypatch.setattr(torch, "compile", FailingCompile)
    monkeypatch.setattr(NoisyLine, "training_step", lambda self, batch, engine: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        fit_line(tmp_path, compile=True)


def test_a_task_that_steps_itself_has_its_networks_compiled_in_place(tmp_path, monkeypatch):
    class Manual(NoisyLine):
        automatic_optimization = False

        def configure_optimizers(self):
            self.opt = torch.optim.SGD(self.parameters(), lr=0.1)
            return [self.opt], []

        def training_step(self, batch, engine):
            loss = ((self.line(batch["x"]) - batch["y"]) ** 2).mean()
            engine.backward(loss)
            engine.step(self.opt)
            return {"loss": loss.detach()}

    monkeypatch.setattr(torch, "compile", FailingCompile)
    FailingCompile.calls = 0
    Trainer(config(max_epochs=2, compile=True), tmp_path).fit(Manual(), NoisyPoints(), NoisyPoints(), batch_size=4)
    assert FailingCompile.calls == 1 and Manual().line._compiled_call_impl is None


def fit_line(run_dir, **trainer):
    seed_everything(0)
    task = NoisyLine()
    best = Trainer(config(**trainer), run_dir).fit(task, NoisyPoints(), NoisyPoints(), batch_size=4)
    return task, best


def counting_saves(monkeypatch) -> list:
    saved = []
    original = torch.save

    def save(obj, f, *args, **kwargs):
        saved.append(obj["epoch"])
        return original(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save)
    return saved


def test_an_improving_epoch_serialises_its_state_once(tmp_path, monkeypatch):
    saved = counting_saves(monkeypatch)
    Trainer(config(max_epochs=3, monitor_mode="max"), tmp_path).fit(ScriptedRecall([0.2, 0.6, 0.4]), Points(), Points(), batch_size=2)
    assert saved == [0, 1, 2]  # three epochs, two of them improving: three writes
    assert ckpt_io.load(tmp_path / "best.pt")["epoch"] == 1 and ckpt_io.load(tmp_path / "last.pt")["epoch"] == 2
    assert not os.path.samefile(tmp_path / "best.pt", tmp_path / "last.pt")  # last.pt was renamed over, best kept


def test_best_is_last_written_in_the_same_epoch(tmp_path):
    Trainer(config(max_epochs=2, monitor_mode="max"), tmp_path).fit(ScriptedRecall([0.2, 0.6]), Points(), Points(), batch_size=2)
    assert os.path.samefile(tmp_path / "best.pt", tmp_path / "last.pt")
    assert oct((tmp_path / "best.pt").stat().st_mode & 0o777) == oct(0o666 & ~ckpt_io.umask())


def test_without_hard_links_best_is_a_copy(tmp_path, monkeypatch):
    def no_links(*args):
        raise OSError("hard links are not supported here")

    monkeypatch.setattr(os, "link", no_links)
    Trainer(config(max_epochs=2, monitor_mode="max"), tmp_path).fit(ScriptedRecall([0.2, 0.6]), Points(), Points(), batch_size=2)
    assert not os.path.samefile(tmp_path / "best.pt", tmp_path / "last.pt")
    assert (tmp_path / "best.pt").read_bytes() == (tmp_path / "last.pt").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".tmp") == []


def test_a_failed_background_write_stops_the_run_with_its_cause(tmp_path, monkeypatch):
    def disk_full(obj, path):
        raise OSError("No space left on device")

    monkeypatch.setattr(ckpt_io, "save_atomic", disk_full)
    with pytest.raises(RuntimeError, match="writing a checkpoint failed: No space left on device"):
        fit_line(tmp_path)


def test_the_write_holds_the_state_of_when_it_was_submitted(tmp_path, monkeypatch):
    """The next epoch changes the live tensors while the state is written: the file must hold the epoch's."""
    original = torch.save

    def slow_save(obj, f, *args, **kwargs):
        time.sleep(0.3)  # the training thread goes on meanwhile
        return original(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", slow_save)
    weight = torch.zeros(4)
    writer = ckpt_io.CheckpointWriter()
    writer.submit({"task": {"w": weight}, "epoch": 0}, tmp_path / "last.pt", also=(tmp_path / "best.pt",))
    weight.add_(1.0)  # the next step, while the write is in flight
    assert writer._thread is not None and writer._thread.is_alive()  # it is written in the background
    writer.join()
    assert torch.equal(ckpt_io.load(tmp_path / "best.pt")["task"]["w"], torch.zeros(4))


def test_a_checkpoint_is_written_without_zip_crcs_and_torch_is_left_as_it_was(tmp_path):
    zipfile = pytest.importorskip("zipfile")
    config = pytest.importorskip("torch.utils.serialization").config
    before = config.save.compute_crc32
    ckpt_io.save_atomic({"task": {"w": torch.arange(6.0)}}, tmp_path / "last.pt")
    assert config.save.compute_crc32 == before  # the user's own torch.save is untouched
    with zipfile.ZipFile(tmp_path / "last.pt") as archive:
        assert {info.CRC for info in archive.infolist()} == {0}  # torch.load never reads them
    assert torch.equal(ckpt_io.load(tmp_path / "last.pt")["task"]["w"], torch.arange(6.0))
    torch.save({"w": torch.arange(6.0)}, tmp_path / "own.pt")
    with zipfile.ZipFile(tmp_path / "own.pt") as archive:
        assert 0 not in {info.CRC for info in archive.infolist()}


@pytest.mark.parametrize("name", ["auto", "cpu", "cuda", "cuda:1"])
def test_the_trainer_takes_every_device_name_the_apps_take(name):
    assert checked({"device": name}, TrainerConfig, "trainer").device == name  # availability: when the run starts


@pytest.mark.parametrize("name", ["gpu", "mps", "cuda:x", "cuda1"])
def test_a_device_name_no_door_takes_is_refused_by_both(name):
    from geoloc.engine.device import resolve_device

    with pytest.raises(ConfigError, match="trainer.device must be auto, cpu, cuda or cuda:N"):
        checked({"device": name}, TrainerConfig, "trainer")
    with pytest.raises(ValueError):
        resolve_device(name)


def test_a_gpu_this_machine_lacks_is_refused_when_the_run_starts(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="CUDA is not available on this machine"):
        Trainer(config(device="cuda:1"), "unused")
