"""Train a geoloc task. `python train.py` runs the embedded default (cross-view on synthetic data).

Examples: python train.py dataset=cvusa dataset.root=/data/CVUSA
          python train.py task=mmdip
          python train.py -m dataset.alignment=ipt,none   (an ablation sweep)
          torchrun --nproc_per_node=2 train.py trainer.device=cpu
"""

import hydra
from omegaconf import DictConfig

import geoloc.launch.hydra_hooks  # noqa: F401  (registers ${pid:}, used in the default run dir)
from geoloc.launch.refusal import refusals_in_one_line


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> float:
    from geoloc.launch.run import objective, train

    with refusals_in_one_line():  # a ConfigError: one line, no traceback (HYDRA_FULL_ERROR=1 shows it)
        return objective(cfg, train(cfg))  # the value Hydra sweepers optimise (the task's sweep_metric)


if __name__ == "__main__":
    import sys

    from geoloc.launch.hydra_hooks import hydra_overrides_for_rank

    sys.argv += hydra_overrides_for_rank()  # ranks > 0 of torchrun share rank 0's run dir and write nothing
    main()
