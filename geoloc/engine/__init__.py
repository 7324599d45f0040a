"""The small training engine both tasks run on."""

from geoloc.engine.task import Task
from geoloc.engine.trainer import Engine, NonFiniteLossError, Trainer, TrainerConfig, seed_everything

__all__ = ["Engine", "NonFiniteLossError", "Task", "Trainer", "TrainerConfig", "seed_everything"]
