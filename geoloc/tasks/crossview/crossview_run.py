"""Builds the cross-view run from its parsed config: data, task, trainer (train) and from a checkpoint (evaluate)."""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from torch.utils.data import Dataset

from geoloc.config import ConfigError, checked
from geoloc.data.retrieval_split import TILE_LABELS
from geoloc.engine import Trainer, TrainerConfig, seed_everything
from geoloc.engine import checkpoint as ckpt_io
from geoloc.engine import distributed as dist
from geoloc.models.crossview import CrossViewModelConfig
from geoloc.models.unfilled_init import unfilled_init
from geoloc.tasks.crossview import gallery_build as gallery
from geoloc.tasks.crossview.crossview_config import (Components, CrossViewEvaluation, CrossViewTraining, parse_components,
                                           parse_evaluation, parse_training)
from geoloc.tasks.crossview.datasets import EvalData, build, build_eval, calibration_data, known_heading
from geoloc.gallery.folder import check_target
from geoloc.tasks.crossview.legacy import is_old_layout, upgraded_config, upgraded_state, upgraded_refiner
from geoloc.tasks.crossview.refine import METRE_LABELS
from geoloc.tasks.crossview.task import CrossViewTask
from geoloc.tasks.crossview.validation_keys import check_monitor, validation_plan

# what an init_from= run does not take from its source: the loss's state (the GMS queue holds the source data's
# places and descriptors; a learned temperature starts again) and the refiner (a refinement stage starts it afresh
# from a retrieval checkpoint)
INIT_FROM_FRESH = ("loss.", "refiner.")


def build_task(model: CrossViewModelConfig, components: Components, max_epochs: int) -> CrossViewTask:
    """Every component from its config section; a bad name or argument fails here, before any data is read."""
    return CrossViewTask(model, components.backbone, components.head, components.loss, components.optim,
                         components.sampler, max_epochs=max_epochs, refiner=components.refiner,
                         refine=components.refine)


@dataclass
class Run:
    """A training run as train.py builds it, before any epoch: what benchmarks and tools take instead of rebuilding
    it from the parts. `fit()` trains it as train.py does (without the final table and figures)."""

    config: CrossViewTraining
    task: CrossViewTask
    trainer: Trainer
    train_set: Dataset
    val_set: Dataset

    def fit(self, train_set: Dataset | None = None, val_set: Dataset | None = None) -> dict:
        """Trainer.fit over the run's data, or over `train_set` / `val_set` where given (a benchmark's held items)."""
        data = self.config.data
        return self.trainer.fit(self.task, self.train_set if train_set is None else train_set,
                                self.val_set if val_set is None else val_set, batch_size=data.batch_size,
                                val_batch_size=data.val_batch_size or None, resume=self.config.job.ckpt)


def build_run(cfg: DictConfig | CrossViewTraining, run_dir: str | Path) -> Run:
    """The run `cfg` (train.py's composed config, or its parsed CrossViewTraining) describes: seeded, the task
    built (and its init_from= weights loaded), the data read and checked, then the trainer. Nothing is written
    to `run_dir` until the data is there, so a failed start leaves no run dir."""
    run = parse_training(cfg) if isinstance(cfg, DictConfig) else cfg
    run_dir = Path(run_dir)
    seed_everything(run.trainer.seed)
    # a resume replaces every weight with the checkpoint's, and its random state too: no initial weight is drawn
    with unfilled_init() if run.job.ckpt else nullcontext():
        task = build_task(run.model, run.components, run.trainer.max_epochs)
    source = None
    if run.job.init_from:
        source = ckpt_io.init_from(task, run.job.init_from, fresh=INIT_FROM_FRESH)
    refine = run.components.refine
    train_set = build(run.data, run.reader, "train", train=True, augment_seed=run.trainer.seed,
                      views=run.components.views, refine=refine)
    val_set = build_eval(run.data, run.reader, run.data.val_split, refine=refine)
    check_monitor(run.monitor, validation_plan(run.data, run.refine, val_set.split), f"on {val_set.split.name}")
    task.validate_on(val_set.split, heading_search=run.data.random_heading)
    trainer = Trainer(run.trainer, run_dir, run.yaml)
    if source and dist.is_main():  # written once the data is there
        ckpt_io.write_source(run_dir, source)
    trainer.init_from = source
    return Run(run, task, trainer, train_set, val_set)


def train(cfg: DictConfig, run_dir: Path) -> dict:
    """train.py's work: parse the config once, then train (`fit`)."""
    return fit(parse_training(cfg), Path(run_dir))


def fit(run: CrossViewTraining, run_dir: Path) -> dict:
    built = build_run(run, run_dir)
    best = built.fit()
    task, trainer, val_set = built.task, built.trainer, built.val_set
    if dist.is_main():
        print_table(best, f"best validation (epoch {best.get('epoch')}), {len(val_set)} queries, {val_set.split.name}")
        print(f"checkpoints: {run_dir / 'best.pt'}  {run_dir / 'last.pt'}")
        if run.job.figures and (run_dir / "best.pt").is_file():
            from geoloc.tasks.crossview.figures import crossview_figures

            state = ckpt_io.load(run_dir / "best.pt")
            ckpt_io.load_task_state(task, state, run_dir / "best.pt")
            crossview_figures(task, known_heading(val_set), run_dir, trainer.device,
                              run.data.val_batch_size or run.data.batch_size)
    return best


def sweep_metric(cfg: DictConfig) -> str:
    """The key of train()'s metrics a Hydra sweep optimises: the one that selects best.pt (trainer.monitor, else
    the task's own, R@1)."""
    return OmegaConf.select(cfg, "trainer.monitor") or CrossViewTask.monitor


def evaluate(cfg: DictConfig, state: dict) -> dict:
    """evaluate.py's work: rebuild model and transforms from the checkpoint's config, score a split; the launcher
    writes the metrics to `metrics_out`."""
    stored = stored_config(state)
    run = parse_evaluation(cfg, stored)
    task = loaded_task(run.model, run.components, stored, state, run.job.ckpt)
    return score(run, task)


def score(run: CrossViewEvaluation, task: CrossViewTask, eval_data: EvalData | None = None) -> dict:
    """The metrics of `task` on the split `run` names, or on `eval_data` when given (the robustness table's gallery
    padded with distractors: datasets.padded)."""
    if run.gallery.save and dist.is_main():  # before the data is read: a taken folder costs nothing
        check_target(run.gallery.save, run.gallery.overwrite)
    if eval_data is None:
        eval_data = build_eval(run.data, run.reader, run.data.split, refine=run.components.refine)
    task.validate_on(eval_data.split, heading_search=run.data.random_heading)
    trainer = evaluation_trainer(run)
    task.to(trainer.device)
    if run.gallery.save or run.gallery.load:  # a saved GalleryIndex (torch / FAISS flat / IVF-PQ)
        if run.data.random_heading:
            raise ConfigError("gallery.save / gallery.load encode each query once, at its known heading; with "
                              "dataset.random_heading=true (K candidate headings per query) evaluate without gallery.*")
        meta = {"ckpt": str(Path(run.job.ckpt).resolve()), "dataset": run.data.name,
                "model_fingerprint": ckpt_io.weights_fingerprint(task.model)}
        held_out = calibration_data(run.data, run.reader, run.components.refine) if run.gallery.save else None
        metrics = gallery.evaluate(task, trainer.engine, eval_data, run.batch_size, run.gallery, meta, held_out,
                                   run.data.fov, run.run_dir)
    else:
        metrics = trainer.validate(task, task.val_dataloaders(eval_data, run.batch_size, trainer.engine))
    metrics["num_queries"] = len(eval_data)
    metrics.setdefault("num_references", eval_data.split.num_references)
    if dist.is_main():
        print_table(metrics, f"{eval_data.split.name} ({len(eval_data)} queries), ckpt {run.job.ckpt}")
    return metrics


def evaluation_trainer(run: CrossViewEvaluation) -> Trainer:
    """The engine an evaluation scores with (evaluate.py, geoloc bench): its device, workers and progress bar, and
    the run's autocast (trainer.precision on CUDA, trainer.cpu_precision on the CPU); it trains nothing."""
    return Trainer(TrainerConfig(device=run.job.device, num_workers=run.job.num_workers, progress=run.job.progress,
                                 precision=run.precision, cpu_precision=run.cpu_precision), run_dir=run.run_dir or ".")


def stored_config(state: dict) -> DictConfig:
    """A checkpoint's config in today's layout (older layouts upgraded: legacy.py)."""
    stored = OmegaConf.create(state["config"])
    return upgraded_config(stored) if is_old_layout(stored) else upgraded_refiner(stored)


def restored_task(state: dict, ckpt, stored: DictConfig) -> CrossViewTask:
    """The task `stored` (the checkpoint's config, stored_config) describes, with the checkpoint's weights, on the
    CPU. `ckpt` names the file in errors. Used by the apps' CrossViewEncoder (encoder.py)."""
    model = checked(stored.model, CrossViewModelConfig, "model")
    return loaded_task(model, parse_components(stored), stored, state, ckpt)


def loaded_task(model: CrossViewModelConfig, components: Components, stored: DictConfig, state: dict,
                ckpt) -> CrossViewTask:
    """The task built from a checkpoint's config and given its weights. Built under unfilled_init: no random
    initial weight is drawn, as the strict load that follows replaces every one (unfilled_init.py)."""
    with unfilled_init():
        task = build_task(model, components, _max_epochs(stored))
    return with_weights(task, state, ckpt)


def with_weights(task: CrossViewTask, state: dict, ckpt) -> CrossViewTask:
    """`task` with checkpoint `state`'s weights (older layouts' names upgraded: legacy.py)."""
    if is_old_layout(OmegaConf.create(state["config"])):
        state = {**state, "task": upgraded_state(state["task"])}
    ckpt_io.load_task_state(task, state, ckpt, hint="Was it written by another task or an edited config? "
                            "Use it with the config it was trained with.")
    return task


def _max_epochs(stored: DictConfig) -> int:
    return int(OmegaConf.select(stored, "trainer.max_epochs") or 1)


def print_table(metrics: dict, title: str) -> None:
    """Recall in %, the other metrics as they are; then the label set behind the metres, where there are any."""
    keys = [k for k in metrics if isinstance(metrics[k], float) and k != "reference_spread"]
    print(f"\n{title}")
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    print("| " + " | ".join(_fmt(k, metrics[k]) for k in keys) + " |")
    if METRE_LABELS in metrics:
        labels = metrics[METRE_LABELS]
        print(f"fine_* metres against {labels}: {TILE_LABELS.get(labels, 'a label set geoloc does not know')}")


def _fmt(key: str, value: float) -> str:
    if key.startswith("R@") or key in ("hit_rate", "AP") or key.startswith(("within_", "heading_within_", "fine_within_",
                                                                          "e2e_within_")):
        return f"{value * 100:.2f}"
    return f"{value:.4g}"
