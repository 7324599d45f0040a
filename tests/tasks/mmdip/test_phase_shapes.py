"""dataset.image_size is checked against the networks of both phases when the config is parsed: a size phase 2's
U-Net (or PatchGAN, or phase 1's segmenter) cannot take fails before phase 1 trains, naming both keys and the sides
that fit. It trained all of phase 1 and failed as phase 2 started."""

import pytest
import torch
from geoloc.config import ConfigError
from geoloc.tasks import mmdip
from geoloc.tasks.mmdip.pipeline import parse

from conftest import compose_train
from helpers.dynamic_data import TINY_MMDIP, write_tiny_dynamic


@pytest.mark.parametrize("overrides,match", [
    (["dataset.image_size=[48,48]"],
     r"dataset.image_size=\[48, 48\] does not fit phase 2's generator .*task.translation.num_downs=5: .*divisible by "
     r"32.* Sides it takes .*: 32, 64, 96, 128, 160, 192 and more\. Change dataset.image_size or "
     r"task.translation.num_downs \(num_downs=4 takes 48x48\)"),
    (["dataset.image_size=[16,16]", "task.translation.num_downs=4"],
     r"dataset.image_size=\[16, 16\] does not fit phase 2's discriminator \(a PatchGAN\), set by "
     r"task.translation.d_layers=3: .*Sides it takes .*: 24, 32, 40"),
    (["dataset.image_size=[48,48]", "task.translation.num_downs=4", "task.segmentation.model=fcn"],
     r"\[48, 48\] does not fit phase 1's segmenter, set by task.segmentation.model=fcn: .*: 32, 64"),
    (["dataset.image_size=[64,48]", "task.segmentation.model=unet", "+task.segmentation.unet.num_downs=5",
      "task.translation.num_downs=4"],
     r"set by task.segmentation.model=unet, task.segmentation.unet.num_downs=5: .*Change dataset.image_size or "
     r"task.segmentation.model / task.segmentation.unet.num_downs"),
])
def test_a_size_a_phase_cannot_take_is_refused_at_parse(tmp_path, overrides, match):
    with pytest.raises(ConfigError, match=match):
        parse(compose_train(["task=mmdip", *overrides, f"run_dir={tmp_path}"]))


def test_the_check_draws_no_random_numbers_and_passes_sizes_that_fit(tmp_path):
    state = torch.get_rng_state()
    for size in ("[64,64]", "[32,96]"):
        parse(compose_train(["task=mmdip", f"dataset.image_size={size}", f"run_dir={tmp_path}"]))
    parse(compose_train(["task=mmdip", "experiment=paper_mmdip", f"run_dir={tmp_path}"]))  # 512 x 512, 8 downs
    assert torch.equal(state, torch.get_rng_state())


def test_training_stops_before_phase_1(tmp_path, one_thread):
    root = write_tiny_dynamic(tmp_path / "dyn", n_train=2, n_val=2)
    run = tmp_path / "run"
    cfg = compose_train([*TINY_MMDIP, "task.translation.num_downs=5", "dataset.image_size=[48,48]",
                         f"dataset.root={root}", f"run_dir={run}"])
    with pytest.raises(ConfigError, match="task.translation.num_downs=5"):
        mmdip.train(cfg, run)
    assert not (run / "phase1").exists()
