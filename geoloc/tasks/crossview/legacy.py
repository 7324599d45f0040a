"""The cross-view checkpoint layouts, and the upgrade from the first to the current one, so `evaluate.py`, export and
localize read a checkpoint of either. The weights themselves are the same in both.

format 1  one network section, `model: {name: msae_vgg16, width, pretrained, batchnorm, msae, dim, ...}`, and the
          GMS queue's buffers under `queue.*`;
format 2  registered components: `backbone: {name: vgg16, ...}`, `head: {name: msae | fc, ...}`, `model: {dim}`,
          and the queue's buffers under `loss.queue.*`.

A correlation refiner stored before its `overlap` key existed divided every score by the whole window: it keeps
that, so its figures stay as they were measured. A refiner stored with `scale_jitter` (a training augmentation of the
ground scale that one development version had, 2026-11-27, and that never acts at evaluation) loads without it.
Both are `upgraded_refiner`.
"""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

OLD_MODEL = "msae_vgg16"
BACKBONE_KEYS = ("width", "pretrained", "weights_path", "batchnorm")


def is_old_layout(stored: DictConfig) -> bool:
    return OmegaConf.select(stored, "model.name") == OLD_MODEL


def upgraded_config(stored: DictConfig) -> DictConfig:
    if not is_old_layout(stored):
        return stored
    cfg = OmegaConf.to_container(stored, resolve=False)
    model = cfg.pop("model")
    cfg["backbone"] = {"name": "vgg16", **{k: model[k] for k in BACKBONE_KEYS if k in model}}
    msae = model.get("msae", True)
    head = {"name": "msae" if msae else "fc", "proj_channels": model.get("proj_channels", 64),
            "pool": model.get("pool", 8)}
    if msae:
        head["scale_channels"] = model.get("scale_channels", 64)
    cfg["head"] = head
    cfg["model"] = {"dim": model.get("dim", 4096), "shared": False}
    cfg.setdefault("sampler", {"name": "shuffle"})
    return OmegaConf.create(cfg)


def upgraded_refiner(stored: DictConfig) -> DictConfig:
    """`stored` with `refiner.overlap: window` where a correlation refiner's section predates the key, and without
    the dropped training-only `refiner.scale_jitter`."""
    refiner = OmegaConf.select(stored, "refiner")
    if refiner is None or refiner.get("name") != "correlation":
        return stored
    if "overlap" in refiner and "scale_jitter" not in refiner:
        return stored
    cfg = OmegaConf.to_container(stored, resolve=False)
    cfg["refiner"].setdefault("overlap", "window")
    cfg["refiner"].pop("scale_jitter", None)
    return OmegaConf.create(cfg)


def upgraded_state(task_state: dict) -> dict:
    return {("loss." + k if k.startswith("queue.") else k): v for k, v in task_state.items()}
