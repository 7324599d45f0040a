"""Builds the cross-view run from a config: data, task, trainer (train) and from a checkpoint (evaluate)."""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from geoloc.config import checked, to_yaml
from geoloc.data import crossview as data
from geoloc.engine import Trainer, TrainerConfig, seed_everything
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine import distributed as dist
from geoloc.engine import resume
from geoloc.models.crossview import CrossViewModelConfig
from geoloc.tasks import crossview_gallery
from geoloc.tasks.crossview import CrossViewTask, OptimConfig, TripletLossConfig
from geoloc.tasks.crossview_gallery import GalleryConfig

# transform settings that must match what the network was trained on; evaluate always takes them from the ckpt
TRANSFORM_KEYS = ("alignment", "aerial_size", "pano_size")
# what an init_from= run does not take from its source: the GMS queue holds the source data's places and descriptors
INIT_FROM_FRESH = ("queue.",)


def build_task(cfg: DictConfig) -> CrossViewTask:
    return CrossViewTask(checked(cfg.model, CrossViewModelConfig, "model"),
                         checked(cfg.loss, TripletLossConfig, "loss"),
                         checked(cfg.optim, OptimConfig, "optim"))


def train(cfg: DictConfig, run_dir: Path) -> dict:
    data_cfg = checked(cfg.dataset, data.CrossViewDataConfig, "dataset")
    trainer_cfg = checked(cfg.trainer, TrainerConfig, "trainer")
    if cfg.get("ckpt"):
        resume.checked_resume(cfg)  # before any data is generated or checked
    seed_everything(trainer_cfg.seed)
    task = build_task(cfg)  # fails on a bad model/loss/optim config before any data is generated
    source = None
    if cfg.get("init_from"):
        source = resume.init_from(task, cfg.init_from, fresh=INIT_FROM_FRESH)
    train_set = data.build(data_cfg, "train", train=True, augment_seed=trainer_cfg.seed)
    val_set = data.build(data_cfg, "val", train=False)
    trainer = Trainer(trainer_cfg, run_dir, to_yaml(cfg))
    if source and dist.is_main():  # written once the data is there: a failed start leaves no run dir
        resume.write_source(run_dir, source)
    trainer.init_from = source
    best = trainer.fit(task, train_set, val_set, batch_size=data_cfg.batch_size,
                       val_batch_size=data_cfg.val_batch_size or None, resume=cfg.get("ckpt"))
    if dist.is_main():
        print_table(best, f"best validation (epoch {best.get('epoch')}), {len(val_set)} queries")
        print(f"checkpoints: {run_dir / 'best.pt'}  {run_dir / 'last.pt'}")
        if cfg.get("figures", True) and (run_dir / "best.pt").is_file():
            from geoloc.eval.figures import crossview_figures

            state = ckpt_io.load(run_dir / "best.pt")
            ckpt_io.load_task_state(task, state, run_dir / "best.pt")
            crossview_figures(task, val_set, run_dir, trainer.device, data_cfg.val_batch_size or data_cfg.batch_size)
    return best


def evaluate(cfg: DictConfig, state: dict) -> dict:
    """Rebuild model and transforms from the checkpoint's config, score a split, write `metrics_out`."""
    stored = OmegaConf.create(state["config"])
    data_section = merged_dataset(stored.dataset, cfg.get("dataset"))
    data_cfg = checked(data_section, data.CrossViewDataConfig, "dataset")
    task = build_task(stored)
    ckpt_io.load_task_state(task, state, cfg.ckpt, hint="Was it written by another task or an edited config? "
                            "Evaluate it with the config it was trained with.")
    dataset = data.build(data_cfg, data_cfg.split, train=False)
    trainer = Trainer(TrainerConfig(device=cfg.get("device", "auto"), num_workers=cfg.get("num_workers", 0),
                                    progress=cfg.get("progress", True)), run_dir=cfg.get("run_dir", "."))
    task.to(trainer.device)
    batch_size = data_cfg.val_batch_size or data_cfg.batch_size
    gallery_cfg = checked(cfg.get("gallery") or {}, GalleryConfig, "gallery")
    if gallery_cfg.save or gallery_cfg.load:  # a saved GalleryIndex (torch / FAISS flat / IVF-PQ)
        meta = {"ckpt": str(cfg.ckpt), "dataset": f"{data_cfg.name} {data_cfg.split} {data_cfg.root}"}
        metrics = crossview_gallery.evaluate(task, trainer, dataset, batch_size, gallery_cfg, meta)
    else:
        metrics = trainer.validate(task, trainer.loader(dataset, batch_size, train=False))
    metrics["num_queries"] = len(dataset)
    if dist.is_main():
        print_table(metrics, f"{data_cfg.name} {data_cfg.split} ({len(dataset)} queries), ckpt {cfg.ckpt}")
        if cfg.get("metrics_out"):
            out = Path(cfg.metrics_out)
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(metrics, indent=2) + "\n")
    return metrics


def merged_dataset(stored: DictConfig, requested: DictConfig | None) -> DictConfig:
    """The stored dataset config, overlaid with what the user asked for at evaluation (name, root, split...),
    except the transform keys, which must stay as trained."""
    section = OmegaConf.to_container(stored, resolve=True)
    overlay = OmegaConf.to_container(requested, resolve=True) if requested else {}
    if overlay.get("name") not in (None, section.get("name")):
        section["root"] = None  # another dataset never inherits the trained one's root; its schema then asks for one
    for key, value in overlay.items():
        if value is not None and key not in TRANSFORM_KEYS:
            section[key] = value
    return OmegaConf.create(section)


def print_table(metrics: dict, title: str) -> None:
    keys = [k for k in metrics if k.startswith("R@")]
    print(f"\n{title}")
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    print("| " + " | ".join(f"{metrics[k] * 100:.2f}" for k in keys) + " |")


