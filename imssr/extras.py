"""Optional dependencies: training and evaluating one run need none of them.

Each is imported where it is used, through :func:`require`, so that a missing one is one line
naming the extra that installs it (pyproject.toml's optional dependencies).
"""
from __future__ import annotations

import importlib
from types import ModuleType

from imssr.errors import ImssrError


def require(module: str, extra: str) -> ModuleType:
    """``import module``, or a one-line :class:`ImssrError` naming ``extra``."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ImssrError(f"{module.split('.')[0]} is not installed (needed by imssr {extra}): "
                         f"pip install 'imssr[{extra}]'  ({exc})") from None
