"""Export a cross-view checkpoint's encoders: python export.py ckpt=outputs/.../best.pt [format=onnx] [out=DIR]
[opset=N] [overwrite=true]. Writes query.onnx, reference.onnx and encoders.json (what each file expects)."""

import hydra

import geoloc.launch.hydra_hooks  # noqa: F401  (the schema nodes every conf/ file extends)
from omegaconf import DictConfig
from geoloc.launch.refusal import refusals_in_one_line


@hydra.main(version_base="1.3", config_path="conf", config_name="export")
def main(cfg: DictConfig) -> None:
    from geoloc.apps.export.onnx_export import export

    with refusals_in_one_line():  # a ConfigError: one line, no traceback (HYDRA_FULL_ERROR=1 shows it)
        export(cfg)


if __name__ == "__main__":
    main()
