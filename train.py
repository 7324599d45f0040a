"""Train a geoloc task. `python train.py` runs the embedded default (cross-view on synthetic data).

Examples: python train.py dataset=cvusa dataset.root=/data/CVUSA
          python train.py task=mmdip
          python train.py -m dataset.alignment=ipt,none   (an ablation sweep)
          torchrun --nproc_per_node=2 train.py trainer.device=cpu
"""

import hydra
from omegaconf import DictConfig

import geoloc.launch.hydra_hooks  # noqa: F401  (registers ${pid:}, used in the default run dir)


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> float:
    from geoloc.launch.run import train

    best = train(cfg)
    # the value Hydra sweepers optimise: the metric that selected best.pt where the run names one (trainer.monitor:
    # fine_median_m for the refinement stage), else the cross-view task's R@1
    monitor = cfg.trainer.get("monitor") or "R@1"
    return float(best.get(monitor, 0.0))


if __name__ == "__main__":
    import sys

    from geoloc.launch.hydra_hooks import hydra_overrides_for_rank

    sys.argv += hydra_overrides_for_rank()  # ranks > 0 of torchrun share rank 0's run dir and write nothing
    main()
