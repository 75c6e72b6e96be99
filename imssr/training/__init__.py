"""Training and evaluation loops, logs and the trainer's part of checkpoints.

The names below load their modules (and torch) on first use, so that a light part of the package
(:mod:`imssr.training.stop`, the CLI's signal handling) imports without them.
"""
__all__ = ["Trainer", "build_agent", "resolve_device", "evaluate", "eval_row", "evaluate_run"]

_HOMES = {"Trainer": "loop", "build_agent": "build", "resolve_device": "build", "evaluate": "evaluate",
          "eval_row": "evaluate", "evaluate_run": "evaluate"}


def __getattr__(name: str):
    if name in _HOMES:
        import importlib

        return getattr(importlib.import_module(f"imssr.training.{_HOMES[name]}"), name)
    raise AttributeError(f"module 'imssr.training' has no attribute {name!r}")
