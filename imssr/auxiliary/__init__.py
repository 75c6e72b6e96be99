"""Auxiliary self-supervised tasks, registered by name (:mod:`~imssr.auxiliary.registry`).

Each task is two modules: ``<name>_spec.py`` (its settings, rules and preset rows; no torch),
which the config reads, and ``<name>.py``, its torch module, which the agent builds.  Importing
this package imports no torch: the task classes load on first use.
"""
import importlib

from imssr.auxiliary.registry import AUX_PLUGINS, AUX_TASKS, make_aux

_LAZY = {"AuxiliaryTask": "base", "SharedNetworks": "base", "CURL": "curl", "SODA": "soda", "PAD": "pad",
         "SVEA": "svea"}
"""Name -> the module of this package that defines it."""

__all__ = ["AuxiliaryTask", "SharedNetworks", "CURL", "SODA", "PAD", "SVEA", "AUX_PLUGINS", "AUX_TASKS", "make_aux"]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'imssr.auxiliary' has no attribute {name!r}")
