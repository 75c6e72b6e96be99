"""Auxiliary self-supervised tasks, registered by name (:mod:`~imssr.auxiliary.registry`).

Each task is two modules: ``<name>_spec.py`` (its settings, rules and preset rows; no torch),
which the config reads, and ``<name>.py``, its torch module, which the agent builds.  Importing
this package imports no torch: the task classes load on first use.
"""
import importlib

from imssr.auxiliary.registry import AUX_PLUGINS, AUX_TASKS, make_aux

_LAZY = {"AuxiliaryTask": "imssr.auxiliary.base", "SharedNetworks": "imssr.auxiliary.base",
         "CURL": "imssr.auxiliary.curl", "SODA": "imssr.auxiliary.soda", "PAD": "imssr.auxiliary.pad",
         "SVEA": "imssr.auxiliary.svea"}

__all__ = ["AuxiliaryTask", "SharedNetworks", "CURL", "SODA", "PAD", "SVEA", "AUX_PLUGINS", "AUX_TASKS", "make_aux"]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'imssr.auxiliary' has no attribute {name!r}")
