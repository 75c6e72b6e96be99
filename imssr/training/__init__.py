"""Training and evaluation loops, logs and checkpoints."""
from imssr.training.evaluate import eval_row, evaluate
from imssr.training.loop import Trainer, build_agent, resolve_device

__all__ = ["Trainer", "build_agent", "resolve_device", "evaluate", "eval_row"]
