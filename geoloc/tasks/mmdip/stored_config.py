"""The layouts of the config an MMDIP checkpoint stores, and the upgrade from one to the next, so that a checkpoint
written in either evaluates. The weights are the same in both.

format 1  the segmenters' keys flat in task.segmentation (unet_num_downs, unet_ngf, fcn_width, each read only by
          the segmenter it names), the generator loss named by task.translation.loss_weights, and the synthetic
          layout's keys (preset, train_size, val_size, view_size, seed, workers) in every dataset section, read
          only by dataset=dynamic;
format 2  each segmenter's keys under task.segmentation.<segmenter>, the generator loss a section
          task.translation.generator_loss with its `name`, and a dataset section holding the keys its reader takes.
"""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

FORMAT_1_SEGMENTER_KEYS = {"unet_num_downs": ("unet", "num_downs"), "unet_ngf": ("unet", "ngf"),
                           "fcn_width": ("fcn", "width")}
FORMAT_1_SYNTHETIC_KEYS = ("preset", "train_size", "val_size", "view_size", "seed", "workers")


def is_format_1(cfg: dict) -> bool:
    task = cfg.get("task") or {}
    return ("loss_weights" in (task.get("translation") or {})
            or any(key in (task.get("segmentation") or {}) for key in FORMAT_1_SEGMENTER_KEYS))


def format_1_to_2(cfg: dict) -> dict:
    """A format-1 config (a plain dict) in format 2."""
    task = dict(cfg.get("task") or {})
    segmentation = dict(task.get("segmentation") or {})
    for key, (segmenter, own_key) in FORMAT_1_SEGMENTER_KEYS.items():
        if key in segmentation:
            segmentation.setdefault(segmenter, {})[own_key] = segmentation.pop(key)
    translation = dict(task.get("translation") or {})
    if "loss_weights" in translation:
        translation["generator_loss"] = {"name": translation.pop("loss_weights")}
    dataset = dict(cfg.get("dataset") or {})
    if dataset.get("name", "dynamic") != "dynamic":
        dataset = {k: v for k, v in dataset.items() if k not in FORMAT_1_SYNTHETIC_KEYS}
    return {**cfg, "task": {**task, "segmentation": segmentation, "translation": translation}, "dataset": dataset}


def upgraded_config(stored: DictConfig) -> DictConfig:
    """The stored config in the current format (format 2)."""
    cfg = OmegaConf.to_container(stored, resolve=False)
    return OmegaConf.create(format_1_to_2(cfg) if is_format_1(cfg) else cfg)
