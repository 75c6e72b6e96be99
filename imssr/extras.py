"""Optional dependencies: training and evaluating one run need none of them.

``imssr sweep`` needs Ray (the ``sweep`` extra; ``--launcher slurm``: submitit, the ``slurm``
extra), ``imssr report``'s IQM (5 seeds per task or more) needs rliable and the pandas it reads
with (the ``report`` extra), ``--logger wandb`` needs wandb (the ``wandb`` extra).  Each is
imported where it is used, through :func:`require`, so that a missing one is one line naming the
extra that installs it: an error, or a warning where the rest of the command goes on (a report
without its IQM).
"""
from __future__ import annotations

import importlib
from types import ModuleType

from imssr.errors import ImssrError

EXTRAS = {"sweep": ("ray",), "report": ("rliable", "pandas"), "wandb": ("wandb",), "slurm": ("submitit",)}
"""Extra -> the top-level modules it installs (pyproject.toml's optional dependencies)."""


def require(module: str, extra: str) -> ModuleType:
    """``import module``, or a one-line :class:`ImssrError` naming ``extra``."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ImssrError(f"{module.split('.')[0]} is not installed (needed by imssr {extra}): "
                         f"pip install 'imssr[{extra}]'  ({exc})") from None
