"""One checkpoint on one test set under several protocols: the reference descriptors are encoded once, and only the
queries again for each FoV or heading. Each protocol's config is evaluate.py's own (composed from geoloc/conf/evaluate.yaml,
parsed by config.parse_evaluation), and the metrics come from the task's validation_epoch_end, as in run.score."""

from __future__ import annotations

from dataclasses import replace

from geoloc.config import ConfigError
from geoloc.tasks.crossview.crossview_config import parse_evaluation
from geoloc.tasks.crossview.datasets import ViewImages, read_split, reference_images
from geoloc.tasks.crossview.crossview_run import evaluation_trainer

PROTOCOL_KEYS = ("fov", "random_heading", "heading_steps")  # what may differ between the protocols of a test set


def score_protocols(task, stored, configs: list) -> tuple[list[dict], dict]:
    """([evaluate.py's metrics of each of `configs`], what the split is: {"split", "labels", "num_queries",
    "num_references"}). `configs`: evaluate.py configs of one test set that differ only in PROTOCOL_KEYS; `task`:
    the checkpoint's, restored once (run.restored_task), `stored` its config."""
    runs = [parse_evaluation(cfg, stored) for cfg in configs]
    first = runs[0]
    for run in runs[1:]:
        if replace(run.data, **{k: getattr(first.data, k) for k in PROTOCOL_KEYS}) != first.data:
            raise ConfigError("the protocols of one test set must read the same data; only "
                              f"{', '.join('dataset.' + k for k in PROTOCOL_KEYS)} may differ between them")
    refine = first.components.refine
    if refine is not None and any(run.data.limited_view for run in runs):
        raise ConfigError("the refiner reads full panoramas: a checkpoint with a refiner is benched at FoV 360 with "
                          "the heading known (fovs=[360] headings=[known])")
    split = read_split(first.data, first.reader, first.data.split)
    trainer = evaluation_trainer(first)
    task.to(trainer.device)
    task.validate_on(split)

    def outputs(images: ViewImages, name: str) -> dict:
        return trainer.validation_outputs(task, trainer.engine.loader(images, first.batch_size, train=False), name)

    references = outputs(reference_images(split, first.data, refine), "reference")
    results = []
    for run in runs:
        task.validate_on(split, heading_search=run.data.random_heading)
        queries = ViewImages(split.queries, split.query_view, run.data, heading_search=run.data.random_heading,
                             refine=refine)
        metrics = task.validation_epoch_end({"query": outputs(queries, "query"), "reference": references})
        metrics["num_queries"] = split.num_queries
        metrics.setdefault("num_references", split.num_references)
        results.append(metrics)
    return results, {"split": split.name, "labels": split.tile_labels, "num_queries": split.num_queries,
                     "num_references": split.num_references}
