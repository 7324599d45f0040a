"""Evaluate a checkpoint: python evaluate.py ckpt=outputs/.../best.pt [dataset=cvusa dataset.root=DIR
dataset.split=val] metrics_out=metrics.json. Model and transforms are rebuilt from the checkpoint's config."""

import hydra
from omegaconf import DictConfig

import geoloc.launch.hydra_hooks  # noqa: F401  (registers ${pid:}, used in the default run dir)
from geoloc.launch.refusal import refusals_in_one_line


@hydra.main(version_base="1.3", config_path="conf", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    from geoloc.launch.run import evaluate

    with refusals_in_one_line():  # a ConfigError: one line, no traceback (HYDRA_FULL_ERROR=1 shows it)
        evaluate(cfg)


if __name__ == "__main__":
    main()
