"""Builds the cross-view run from a config: data, task, trainer (train) and from a checkpoint (evaluate)."""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from geoloc.config import ConfigError, checked, to_yaml
from geoloc.tasks.crossview.data_config import SHARED_KEYS, check_reader_keys, shared_config
from geoloc.tasks.crossview.datasets import build, build_eval, known_heading
from geoloc.engine import Trainer, TrainerConfig, seed_everything
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine import distributed as dist
from geoloc.launch import resume
from geoloc.models.crossview import CrossViewModelConfig
from geoloc.tasks.crossview import gallery
from geoloc.tasks.crossview.legacy import is_old_layout, upgraded_config, upgraded_state
from geoloc.tasks.crossview.gallery import GalleryConfig
from geoloc.tasks.crossview.task import CrossViewTask

# transform settings that must match what the network was trained on; evaluate always takes them from the ckpt.
# The view's field of view and heading (fov, random_heading, heading_steps) are not among them: they are the test
# condition, and evaluate.py may set them (conf/evaluate.yaml).
TRANSFORM_KEYS = ("alignment", "aerial_size", "pano_size")
# what an init_from= run does not take from its source: the loss's state (the GMS queue holds the source data's
# places and descriptors; a learned temperature starts again)
INIT_FROM_FRESH = ("loss.",)


def build_task(cfg: DictConfig) -> CrossViewTask:
    """Every component from its config group; a bad name or argument fails here, before any data is read."""
    return CrossViewTask(checked(cfg.model, CrossViewModelConfig, "model"), cfg.backbone, cfg.head, cfg.loss,
                         cfg.optim, cfg.get("sampler"), max_epochs=int(cfg.trainer.max_epochs))


def train(cfg: DictConfig, run_dir: Path) -> dict:
    shared_config(cfg.dataset)  # bad dataset keys fail here, before anything is read or generated
    check_reader_keys(cfg.dataset)
    trainer_cfg = checked(cfg.trainer, TrainerConfig, "trainer")
    if cfg.get("ckpt"):
        resume.checked_resume(cfg)  # before any data is generated or checked
    seed_everything(trainer_cfg.seed)
    task = build_task(cfg)
    source = None
    if cfg.get("init_from"):
        source = resume.init_from(task, cfg.init_from, fresh=INIT_FROM_FRESH)
    data_cfg = shared_config(cfg.dataset)
    train_set = build(cfg.dataset, "train", train=True, augment_seed=trainer_cfg.seed)
    val_set = build_eval(cfg.dataset, data_cfg.val_split)
    trainer = Trainer(trainer_cfg, run_dir, to_yaml(cfg))
    if source and dist.is_main():  # written once the data is there: a failed start leaves no run dir
        resume.write_source(run_dir, source)
    trainer.init_from = source
    best = trainer.fit(task, train_set, val_set, batch_size=data_cfg.batch_size,
                       val_batch_size=data_cfg.val_batch_size or None, resume=cfg.get("ckpt"))
    if dist.is_main():
        print_table(best, f"best validation (epoch {best.get('epoch')}), {len(val_set)} queries, {val_set.split.name}")
        print(f"checkpoints: {run_dir / 'best.pt'}  {run_dir / 'last.pt'}")
        if cfg.get("figures", True) and (run_dir / "best.pt").is_file():
            from geoloc.tasks.crossview.figures import crossview_figures

            state = ckpt_io.load(run_dir / "best.pt")
            ckpt_io.load_task_state(task, state, run_dir / "best.pt")
            crossview_figures(task, known_heading(val_set), run_dir, trainer.device,
                              data_cfg.val_batch_size or data_cfg.batch_size)
    return best


def evaluate(cfg: DictConfig, state: dict) -> dict:
    """Rebuild model and transforms from the checkpoint's config, score a split, write `metrics_out`."""
    task, stored = restored_task(state, cfg.ckpt)
    data_section = merged_dataset(stored.dataset, cfg.get("dataset"))
    data_cfg = shared_config(data_section)
    eval_data = build_eval(data_section, data_cfg.split)
    trainer = Trainer(TrainerConfig(device=cfg.get("device", "auto"), num_workers=cfg.get("num_workers", 0),
                                    progress=cfg.get("progress", True)), run_dir=cfg.get("run_dir", "."))
    task.to(trainer.device)
    batch_size = data_cfg.val_batch_size or data_cfg.batch_size
    gallery_cfg = checked(cfg.get("gallery") or {}, GalleryConfig, "gallery")
    if gallery_cfg.save or gallery_cfg.load:  # a saved GalleryIndex (torch / FAISS flat / IVF-PQ)
        if data_cfg.random_heading:
            raise ConfigError("gallery.save / gallery.load encode each query once, at its known heading; with "
                              "dataset.random_heading=true (K candidate headings per query) evaluate without gallery.*")
        meta = {"ckpt": str(Path(cfg.ckpt).resolve()), "dataset": f"{data_cfg.name} {data_cfg.split} {data_cfg.root}",
                "model_fingerprint": ckpt_io.weights_fingerprint(task.model)}
        metrics = gallery.evaluate(task, trainer.engine, eval_data, batch_size, gallery_cfg, meta)
    else:
        metrics = trainer.validate(task, task.val_dataloaders(eval_data, batch_size, trainer.engine))
    metrics["num_queries"] = len(eval_data)
    metrics.setdefault("num_references", eval_data.split.num_references)
    if dist.is_main():
        print_table(metrics, f"{eval_data.split.name} ({len(eval_data)} queries), ckpt {cfg.ckpt}")
        if cfg.get("metrics_out"):
            out = Path(cfg.metrics_out)
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(metrics, indent=2) + "\n")
    return metrics


def load_checkpoint(ckpt, use: str) -> tuple[CrossViewTask, DictConfig, dict]:
    """(task with the weights loaded, its config, the checkpoint dict) of a cross-view checkpoint file; another
    task's checkpoint is refused, naming `use` (what wanted it: export.py, localize)."""
    state = ckpt_io.load(ckpt)
    task_name = OmegaConf.select(OmegaConf.create(state.get("config") or "{}"), "task.name") or "crossview"
    if task_name != "crossview":
        raise ConfigError(f"ckpt={ckpt} is a task={task_name} checkpoint; {use} takes cross-view checkpoints "
                          "(task=crossview) only")
    task, stored = restored_task(state, ckpt)
    return task, stored, state


def restored_task(state: dict, ckpt) -> tuple[CrossViewTask, DictConfig]:
    """The task a checkpoint's config describes, with the checkpoint's weights, on the CPU, and that config (older
    layouts upgraded: geoloc/tasks/crossview/legacy.py). `ckpt` names the file in errors. Used by evaluate, export
    and localize."""
    stored = OmegaConf.create(state["config"])
    if is_old_layout(stored):
        stored, state = upgraded_config(stored), {**state, "task": upgraded_state(state["task"])}
    task = build_task(stored)
    ckpt_io.load_task_state(task, state, ckpt, hint="Was it written by another task or an edited config? "
                            "Use it with the config it was trained with.")
    return task, stored


def merged_dataset(stored: DictConfig, requested: DictConfig | None) -> DictConfig:
    """The stored dataset config, overlaid with what the user asked for at evaluation (name, root, split...),
    except the transform keys, which must stay as trained. Another dataset keeps only the shared keys of the
    stored one: its reader's own keys come from the request (or the reader's defaults)."""
    section = OmegaConf.to_container(stored, resolve=True)
    overlay = OmegaConf.to_container(requested, resolve=True) if requested else {}
    if overlay.get("name") not in (None, section.get("name")):
        section = {k: v for k, v in section.items() if k in SHARED_KEYS and k != "module"}
        section["root"] = None  # another dataset never inherits the trained one's root
    for key, value in overlay.items():
        if value is not None and key not in TRANSFORM_KEYS:
            section[key] = value
    return OmegaConf.create(section)


def print_table(metrics: dict, title: str) -> None:
    """Recall in %, the other metrics as they are."""
    keys = [k for k in metrics if isinstance(metrics[k], float) and k != "reference_spread"]
    print(f"\n{title}")
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    print("| " + " | ".join(_fmt(k, metrics[k]) for k in keys) + " |")


def _fmt(key: str, value: float) -> str:
    if key.startswith("R@") or key in ("hit_rate", "AP") or key.startswith(("within_", "heading_within_")):
        return f"{value * 100:.2f}"
    return f"{value:.4g}"
