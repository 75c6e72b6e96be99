"""Training and evaluation loops, logs and checkpoints."""
import importlib

__all__ = ["Trainer", "build_agent", "resolve_device", "evaluate", "eval_row", "evaluate_run"]

_WHERE = {"Trainer": "loop", "build_agent": "build", "resolve_device": "build", "evaluate": "evaluate",
          "eval_row": "evaluate", "evaluate_run": "evaluate"}


def __getattr__(name: str):
    # Resolved on first use: importing one module of this package (the checkpoint file format,
    # the lock) must not load the trainer, which itself reads run directories through them.
    if name in _WHERE:
        return getattr(importlib.import_module(f"imssr.training.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'imssr.training' has no attribute {name!r}")
