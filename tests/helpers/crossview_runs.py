"""Small cross-view training runs the end-to-end and resume tests share."""

from __future__ import annotations

import json

from geoloc.launch import run
from geoloc.tasks.crossview.task import CrossViewTask

from conftest import TINY, compose_train
from helpers.kill import run_killed_at


def train_cfg(root, run_dir, *extra):
    return compose_train([*TINY, f"dataset.root={root}", f"run_dir={run_dir}", *extra])


def val_records(run_dir):
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [json.loads(x) for x in lines if '"val/R@1"' in x]


def train_until_killed(cfg, monkeypatch, global_step: int) -> None:
    """run.train(cfg), killed (KeyboardInterrupt) as the step after `global_step` starts."""
    run_killed_at(CrossViewTask, global_step, lambda: run.train(cfg), monkeypatch)


def task_of(cfg):
    """The CrossViewTask a composed train config describes, as train.py builds it (parse, then build)."""
    from geoloc.tasks.crossview.crossview_config import parse_training
    from geoloc.tasks.crossview.crossview_run import build_task

    run = parse_training(cfg)
    return build_task(run.model, run.components, run.trainer.max_epochs)


def pairs_of(section, split: str, train: bool, augment_seed: int = 0):
    """CrossViewPairs of a dataset section (a DictConfig, dict or CrossViewDataConfig), parsed as a run parses it."""
    from geoloc.tasks.crossview.data_config import parse_dataset
    from geoloc.tasks.crossview.datasets import build

    data, reader = parse_dataset(section)
    return build(data, reader, split, train=train, augment_seed=augment_seed)


def eval_data_of(section, split: str):
    """The EvalData of a dataset section, parsed as a run parses it."""
    from geoloc.tasks.crossview.data_config import parse_dataset
    from geoloc.tasks.crossview.datasets import build_eval

    data, reader = parse_dataset(section)
    return build_eval(data, reader, split)


def split_of(section, split: str):
    """The RetrievalSplit of a dataset section, parsed as a run parses it."""
    from geoloc.tasks.crossview.data_config import parse_dataset
    from geoloc.tasks.crossview.datasets import read_split

    data, reader = parse_dataset(section)
    return read_split(data, reader, split)
