"""Training and evaluation loops, logs and the trainer's part of checkpoints."""
from imssr.training.build import build_agent, resolve_device
from imssr.training.evaluate import eval_row, evaluate, evaluate_run
from imssr.training.loop import Trainer

__all__ = ["Trainer", "build_agent", "resolve_device", "evaluate", "eval_row", "evaluate_run"]
