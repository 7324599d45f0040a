"""Localize street images against a saved gallery: python localize.py ckpt=.../best.pt gallery=DIR image=FILE_OR_DIR
[topk=5] [fov=360] [heading=null] [out=DIR]. Prints one JSON line per image and writes them to out/localize.jsonl,
with a picture per image (geoloc/apps/localize/)."""

import hydra
from omegaconf import DictConfig

import geoloc.launch.hydra_hooks  # noqa: F401  (registers ${pid:}, used in the default run dir)
from geoloc.apps.localize.run import LocalizeConfig, localize
from geoloc.launch.refusal import refusals_in_one_line
from geoloc.launch.schemas import store_dataclass

store_dataclass("localize", LocalizeConfig)  # the defaults conf/localize.yaml extends


@hydra.main(version_base="1.3", config_path="conf", config_name="localize")
def main(cfg: DictConfig) -> None:
    with refusals_in_one_line():  # a ConfigError: one line, no traceback (HYDRA_FULL_ERROR=1 shows it)
        localize(cfg)


if __name__ == "__main__":
    main()
