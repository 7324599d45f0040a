"""The MMDIP run: phase 1 (segmentation) -> phase 2 (joint cGAN) -> VPR evaluation, and checkpoint evaluation.

run_dir/phase1/{best,last}.pt   SegmentationTask checkpoints (best = MIoU)
run_dir/phase2/{best,last}.pt   JointTask checkpoints (best = SSIM), start from phase1/best.pt
run_dir/vpr/                    vocabulary.npz, gallery_<split>_<seg>.npz (+ maps), metrics_<split>.json
run_dir/vpr/<dataset>/          the same for dataset=carla4 / emptycities (place protocols: protocol.py)

An evaluation writes its artefacts to its own run dir (the same vpr/ layout), reusing the training run's read
only when they match (retrieval.py); it never writes into the training run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import tempfile
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from geoloc.config import ConfigError, to_yaml
from geoloc.engine import Trainer, TrainerConfig, seed_everything
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine import distributed as dist
from geoloc.tasks.mmdip.mmdip_config import DynamicDataConfig, MMDIPConfig, data_config, parse_sections, task_config
from geoloc.tasks.mmdip.datasets import NUM_CLASSES, STATIC_CLASSES
from geoloc.tasks.mmdip.joint import JointTask
from geoloc.tasks.mmdip.readers import build_reader
from geoloc.tasks.mmdip.retrieval import evaluate_retrieval, model_id, print_recall
from geoloc.tasks.mmdip.segmentation import SegmentationTask, batch_confusion, confusion_metrics
from geoloc.tasks.mmdip.shapes import check_image_size
from geoloc.tasks.mmdip.stored_config import upgraded_config

TRANSFORM_KEYS = ("image_size",)  # must stay as trained


def vpr_dir(run_dir: Path, dataset: str) -> Path:
    """Where a run keeps its retrieval artefacts for `dataset`: vpr/ for the synthetic layout it trains on by
    default, vpr/<dataset>/ for the others, so evaluating another reader never overwrites them."""
    return Path(run_dir) / "vpr" if dataset == "dynamic" else Path(run_dir) / "vpr" / dataset


def parse(cfg: DictConfig) -> tuple[MMDIPConfig, DynamicDataConfig, TrainerConfig]:
    """The run's typed configs, parsed once: the sections and every registered part (segmenter, generator loss,
    reader) against the registry (parse_sections), dataset.image_size against the networks of both phases
    (shapes.py), so an unknown name or key, or a size phase 2 cannot take, fails before any data is read."""
    task_cfg, data_cfg, trainer_cfg = parse_sections(cfg)
    check_image_size(task_cfg, data_cfg)  # phase 2's shapes too: found there, they would cost all of phase 1
    if task_cfg.num_classes != NUM_CLASSES:
        raise ConfigError(f"task.num_classes must be {NUM_CLASSES} (the paper's static classes)")
    if trainer_cfg.monitor is not None or trainer_cfg.monitor_mode != "max":
        # one trainer section drives both phases, whose validations report different keys
        raise ConfigError(f"task=mmdip selects each phase's best.pt by its own metric, the higher the better (phase 1: "
                          f"{SegmentationTask.monitor}, phase 2: {JointTask.monitor}); trainer.monitor="
                          f"{trainer_cfg.monitor} and trainer.monitor_mode={trainer_cfg.monitor_mode} would apply to "
                          "both phases: leave them unset")
    if cfg.get("ckpt") or cfg.get("init_from"):
        raise ConfigError("task=mmdip runs both phases from scratch: resuming with ckpt= or starting from weights "
                          "with init_from= is not supported. Start the run again in a new run dir (leave "
                          "hydra.run.dir at its default).")
    return task_cfg, data_cfg, trainer_cfg


def phase_trainer(trainer_cfg: TrainerConfig, epochs: int, run_dir: Path, yaml: str) -> Trainer:
    """trainer.max_epochs caps each phase's own epoch count."""
    return Trainer(dataclasses.replace(trainer_cfg, max_epochs=min(epochs, trainer_cfg.max_epochs)), run_dir, yaml)


def run_phase1(task_cfg, data_cfg, trainer_cfg, train_set, val_set, fractions, run_dir: Path, yaml: str):
    seed_everything(trainer_cfg.seed)  # each phase's initialisation follows the run's `seed`
    task = SegmentationTask(task_cfg.segmentation, task_cfg.num_classes, fractions)
    trainer = phase_trainer(trainer_cfg, task_cfg.segmentation.epochs, run_dir, yaml)
    best = trainer.fit(task, train_set, val_set, batch_size=task_cfg.segmentation.batch_size,
                       val_batch_size=data_cfg.val_batch_size)
    return task, best


def run_phase2(task_cfg, data_cfg, trainer_cfg, train_set, val_set, fractions, run_dir: Path, yaml: str,
               phase1_ckpt: Path | None):
    seed_everything(trainer_cfg.seed)
    task = JointTask(task_cfg, fractions)
    if phase1_ckpt is not None and task_cfg.translation.init_from_phase1:
        state = ckpt_io.load(phase1_ckpt)["task"]
        task.seg.load_state_dict({k[len("seg."):]: v for k, v in state.items() if k.startswith("seg.")})
    trainer = phase_trainer(trainer_cfg, task_cfg.translation.epochs, run_dir, yaml)
    best = trainer.fit(task, train_set, val_set, batch_size=task_cfg.translation.batch_size,
                       val_batch_size=data_cfg.val_batch_size)
    if (run_dir / "best.pt").is_file():
        task.load_state_dict(ckpt_io.load(run_dir / "best.pt")["task"])
    return task, best, trainer.device


def train(cfg: DictConfig, run_dir: Path) -> dict:
    """Phase 1 -> phase 2 -> VPR evaluation on dataset.split; prints them and returns the retrieval metrics
    (R@K, num_queries, ...) with the phases' best validation metrics under "phase1" and "phase2"."""
    task_cfg, data_cfg, trainer_cfg = parse(cfg)
    run_dir = Path(run_dir)
    yaml = to_yaml(cfg)
    reader = build_reader(data_cfg)
    fractions = reader.class_fractions()  # a reader without labels (emptycities) refuses to train here
    train_set = reader.split("train", train=True, seed=trainer_cfg.seed)  # dataset.seed only picks a world
    val_set = reader.split("val")

    _, best1 = run_phase1(task_cfg, data_cfg, trainer_cfg, train_set, val_set, fractions, run_dir / "phase1", yaml)
    print(f"phase 1 ({task_cfg.segmentation.model}) best: " + _fmt(best1))
    task, best2, device = run_phase2(task_cfg, data_cfg, trainer_cfg, train_set, val_set, fractions,
                                     run_dir / "phase2", yaml, run_dir / "phase1" / "best.pt")
    print(f"phase 2 ({task_cfg.translation.variant}) best: " + _fmt(best2))
    result = {"phase1": best1, "phase2": best2}
    if dist.is_main():
        protocol = reader.place_protocol(data_cfg.split)
        out = evaluate_retrieval(task, protocol, task_cfg.vpr, device, vpr_dir(run_dir, data_cfg.name),
                                 model_id(run_dir / "phase2" / "best.pt"), data_cfg.val_batch_size,
                                 trainer_cfg.num_workers)
        result = {**out["metrics"], **result}  # recall keys at the top, as the cross-view runner returns them
        print_recall(out["metrics"], f"MMDIP retrieval, {data_cfg.split} split, L={task_cfg.vpr.levels}")
        (run_dir / "metrics.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def sweep_metric(cfg: DictConfig) -> str:
    """The key of train()'s result a Hydra sweep optimises: the fused retrieval's R@1 (the phases' own monitors,
    MIoU and SSIM, select their checkpoints; their values sit under "phase1" / "phase2")."""
    return "R@1"


def _fmt(metrics: dict) -> str:
    return "  ".join(f"{k} {v:.4g}" for k, v in metrics.items() if isinstance(v, float) and "IoU_" not in k)


def print_segmentation(metrics: dict, title: str) -> None:
    """Table I's row of one checkpoint: PA, MPA, MIoU, FWIoU, then the IoU of each class present."""
    print(f"\n{title}")
    keys = ("PA", "MPA", "MIoU", "FWIoU")
    print("| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    print("| " + " | ".join(f"{metrics[k]:.4f}" for k in keys) + " |")
    present = [(name, metrics[f"IoU_{c}"]) for c, name in enumerate(STATIC_CLASSES) if f"IoU_{c}" in metrics]
    print("\n| class | IoU |\n|---|---|")
    print("\n".join(f"| {name} | {iou:.4f} |" for name, iou in present))
    absent = [name for c, name in enumerate(STATIC_CLASSES) if f"IoU_{c}" not in metrics]
    if absent:
        print(f"absent from labels and predictions (left out of the means): {', '.join(absent)}")


def _merged_dataset(stored: DictConfig, requested: DictConfig | None) -> DictConfig:
    section = OmegaConf.to_container(stored, resolve=True)
    if requested is not None:
        req = OmegaConf.to_container(requested, resolve=True)
        if req.get("name") and req["name"] != section.get("name"):
            section = {k: v for k, v in section.items() if k in TRANSFORM_KEYS or k == "val_batch_size"}
        section.update({k: v for k, v in req.items() if v is not None and k not in TRANSFORM_KEYS})
    return OmegaConf.create(section)


def load_task(ckpt_path: Path, state: dict | None = None) -> tuple[JointTask | SegmentationTask, MMDIPConfig,
                                                                   DictConfig]:
    """(task with the checkpoint's weights, its task config, its stored config): a JointTask for a phase-2
    checkpoint, a SegmentationTask for a phase-1 one. `state`: the checkpoint, when already loaded."""
    state = state if state is not None else ckpt_io.load(ckpt_path)
    stored = upgraded_config(OmegaConf.create(state["config"]))
    task_cfg = task_config(stored.task)
    uniform = [1.0 / task_cfg.num_classes] * task_cfg.num_classes  # the stored class weights replace these
    if any(k.startswith("generator.") for k in state["task"]):
        task = JointTask(task_cfg, uniform, training=False)
    else:
        task = SegmentationTask(task_cfg.segmentation, task_cfg.num_classes, uniform)
    task.load_state_dict(state["task"])
    return task.eval(), task_cfg, stored


@torch.no_grad()
def evaluate(cfg: DictConfig, state: dict | None = None) -> dict:
    """Score a phase-2 (or phase-1) checkpoint on the dataset asked for (default: the run's own).

    Phase 2, every reader (dynamic, carla4, emptycities): the place protocol of protocol.py, so the recall keys
    + num_queries, the BoW / SPM / dynamic-BoW rows, and L1 / L2 / PSNR / SSIM of the recovered queries against
    their static views; artefacts are written to vpr_dir(cfg.run_dir) (a temporary folder, removed, when the
    config has no run dir) and reused, read only, from the checkpoint's training run (training_run). Phase 1: PA,
    MPA, MIoU, FWIoU and the per-class IoU (needs labels). Each prints its table. `cfg.ckpt` is the checkpoint
    (`state` its loaded contents, when the caller has them); the launcher writes the metrics to `metrics_out`."""
    ckpt_path = Path(cfg.ckpt)
    task, task_cfg, stored = load_task(ckpt_path, state)
    data_cfg = data_config(_merged_dataset(stored.dataset, cfg.get("dataset")))
    is_joint = isinstance(task, JointTask)
    reader = build_reader(data_cfg)
    if not is_joint and not reader.has_labels:
        raise ConfigError(f"{ckpt_path} is a phase-1 (segmentation) checkpoint: it is scored against labels, and "
                          f"dataset={data_cfg.name} has none. Evaluate phase2/best.pt there, or a phase-1 checkpoint "
                          f"on a dataset with labels (dataset=dynamic or dataset=carla4)")
    device = dist.init_from_env(cfg.get("device", "auto"))
    task.to(device)

    if is_joint:
        own = OmegaConf.select(cfg, "run_dir", throw_on_resolution_failure=False)
        training = training_run(ckpt_path)
        if own and training is not None and Path(own).resolve() == training:
            raise ConfigError(f"run_dir={own} is the training run of {ckpt_path}; an evaluation writes to its own run "
                              f"dir (leave hydra.run.dir at its default, or name a new folder)")
        protocol = reader.place_protocol(data_cfg.split)
        with (contextlib.nullcontext(vpr_dir(own, data_cfg.name)) if own
              else tempfile.TemporaryDirectory(prefix="geoloc-mmdip-evaluation-")) as out:
            metrics = evaluate_retrieval(
                task, protocol, task_cfg.vpr, device, Path(out), model_id(ckpt_path), data_cfg.val_batch_size,
                reuse_from=[] if training is None else [vpr_dir(training, data_cfg.name)])["metrics"]
        print_recall(metrics, f"MMDIP retrieval, {data_cfg.name} {data_cfg.split or ''}, ckpt {ckpt_path}")
    else:
        dataset = reader.split(data_cfg.split)
        loader = torch.utils.data.DataLoader(dataset, batch_size=data_cfg.val_batch_size)
        conf = sum(batch_confusion(task.seg(b["dynamic"].to(device)).argmax(1), b["label"].to(device),
                                   task.num_classes).sum(0) for b in loader)
        metrics = confusion_metrics(conf[None])
        print_segmentation(metrics, f"MMDIP phase-1 segmentation ({task_cfg.segmentation.model}), {data_cfg.name} "
                                    f"{data_cfg.split or ''}, ckpt {ckpt_path}")
    return metrics


def training_run(ckpt_path: Path) -> Path | None:
    """The run dir that trained `ckpt_path` (RUN/phase1/*.pt, RUN/phase2/*.pt), or None for a checkpoint
    elsewhere (a copy): its vpr/ artefacts are reused read only, never written by an evaluation."""
    ckpt_path = Path(ckpt_path).resolve()
    return ckpt_path.parent.parent if ckpt_path.parent.name in ("phase1", "phase2") else None
