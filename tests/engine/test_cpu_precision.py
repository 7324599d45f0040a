"""trainer.cpu_precision: the autocast on the CPU, a key of its own (trainer.precision stays CUDA's), taken by the
training step, evaluate.py and the apps alike from the run's stored config."""

from __future__ import annotations

import pytest
import torch
from geoloc.config import ConfigError, checked
from geoloc.engine import Trainer, TrainerConfig
from geoloc.engine import device as device_rules
from geoloc.engine.device import amp_dtype
from geoloc.launch import run
from geoloc.tasks.crossview.crossview_config import parse_evaluation
from geoloc.tasks.crossview.crossview_run import evaluation_trainer, stored_config
from geoloc.engine import checkpoint as ckpt_io
from geoloc.tasks.crossview.encoder import CrossViewEncoder

from conftest import TINY, compose_evaluate, compose_train, write_cvusa
from test_trainer import config

CPU, CUDA = torch.device("cpu"), torch.device("cuda")


def test_each_device_reads_its_own_key():
    assert amp_dtype("32", CPU, "bf16") == torch.bfloat16
    assert amp_dtype("bf16", CPU) is None and amp_dtype("16", CPU, "32") is None  # a GPU recipe's bf16: not here
    assert amp_dtype("32", CUDA, "bf16") is None and amp_dtype("bf16", CUDA, "32") == torch.bfloat16
    assert TrainerConfig().cpu_precision == "32"


@pytest.mark.parametrize("value", ["16", "fp32", "bf16-cpu", "Auto"])
def test_a_cpu_precision_other_than_32_bf16_or_auto_is_refused(value):
    with pytest.raises(ConfigError, match="trainer.cpu_precision must be '32', 'bf16' or 'auto'"):
        checked({"cpu_precision": value}, TrainerConfig, "trainer")


@pytest.mark.parametrize("native, dtype", [(True, torch.bfloat16), (False, None), (None, None)])
def test_auto_is_bf16_only_where_torch_says_the_cpu_has_it(monkeypatch, caplog, tmp_path, native, dtype):
    """auto: bfloat16 where the CPU has a native path, float32 where it would emulate it or torch cannot say, never
    warned of, and said at start-up; the explicit keys and CUDA's autocast do not ask."""
    monkeypatch.setattr(device_rules, "native_cpu_bf16", lambda: native)
    assert amp_dtype("32", CPU, "auto") == dtype
    assert amp_dtype("32", CPU, "bf16") == torch.bfloat16 and amp_dtype("32", CPU, "32") is None
    assert amp_dtype("bf16", CUDA, "auto") == torch.bfloat16 and amp_dtype("32", CUDA, "auto") is None
    with caplog.at_level("INFO", logger="geoloc.engine.device"):
        trainer = Trainer(config(cpu_precision="auto"), tmp_path / "auto")
    assert trainer.amp_dtype == dtype
    said = [r for r in caplog.records if r.name == "geoloc.engine.device"]
    assert [r.levelname for r in said] == ["INFO"]
    assert said[0].getMessage().startswith(f"{tmp_path / 'auto'}: trainer.cpu_precision=auto computes in "
                                           f"{'bfloat16' if native else 'float32'}")


def test_the_training_step_computes_in_bf16_only_when_asked(tmp_path):
    layer, x = torch.nn.Linear(4, 4), torch.randn(2, 4)
    for precision, dtype in (("32", torch.float32), ("bf16", torch.bfloat16)):
        with Trainer(config(cpu_precision=precision), tmp_path / precision).autocast():
            assert layer(x).dtype == dtype, precision


def test_evaluation_and_the_apps_compute_as_the_run_trained(tmp_path):
    root = write_cvusa(tmp_path / "cvusa", n_train=8, n_val=4)
    ckpt = tmp_path / "run" / "last.pt"
    run.train(compose_train([*TINY, f"dataset.root={root}", f"run_dir={ckpt.parent}", "trainer.max_epochs=1",
                             "trainer.cpu_precision=bf16"]))
    stored = stored_config(ckpt_io.load(ckpt))
    evaluation = parse_evaluation(compose_evaluate([f"ckpt={ckpt}", "device=cpu"]), stored)
    assert evaluation.cpu_precision == "bf16" and evaluation_trainer(evaluation).amp_dtype == torch.bfloat16

    encoder = CrossViewEncoder.load(ckpt, device="cpu")
    street = torch.rand(2, 3, 16, 64)
    with torch.no_grad():
        with torch.autocast("cpu", dtype=torch.bfloat16):
            as_trained = encoder.model.query(street).float()
        in_float32 = encoder.model.query(street)
    served = encoder.encode_street(street)
    assert served.dtype == torch.float32 and torch.equal(served, as_trained)
    assert not torch.equal(served, in_float32)  # the comparison can tell the two apart


@pytest.mark.parametrize("native", [False, True, None])
def test_a_bf16_run_on_a_cpu_that_emulates_bf16_is_warned_with_the_way_out(tmp_path, monkeypatch, caplog, native):
    """Only where torch says the CPU has no native bfloat16 path (not where it has one, nor where it cannot say), and
    only for bf16 on the CPU; the warning names the run and the key that turns it off."""
    monkeypatch.setattr(device_rules, "native_cpu_bf16", lambda: native)
    with caplog.at_level("WARNING", logger="geoloc.engine.device"):
        Trainer(config(cpu_precision="32"), tmp_path / "f32")
        assert not caplog.records
        Trainer(config(cpu_precision="bf16"), tmp_path / "bf16")
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == (native is False)
    if warned:
        assert warned[0].startswith(f"{tmp_path / 'bf16'}: the CPU autocast is bfloat16")
        assert "add trainer.cpu_precision=32 (or auto" in warned[0]
    assert not device_rules.warn_emulated_bf16(CUDA, "bf16", "x")  # the GPU's autocast is not this key's


def test_torch_is_asked_whether_this_cpu_has_native_bf16():
    assert device_rules.native_cpu_bf16() in (True, False, None)
