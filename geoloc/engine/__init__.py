"""The small training engine both tasks run on."""

from geoloc.engine.task import Task
from geoloc.engine.step_engine import Engine
from geoloc.engine.trainer import NonFiniteLossError, Trainer
from geoloc.engine.trainer_config import TrainerConfig, seed_everything

__all__ = ["Engine", "NonFiniteLossError", "Task", "Trainer", "TrainerConfig", "seed_everything"]
