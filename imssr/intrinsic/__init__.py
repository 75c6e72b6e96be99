"""Intrinsic rewards: the raw signal of o' (IM-SSR's SSL loss, RND, RE3), then in-batch
normalisation (:class:`IntrinsicReward`) and the beta schedule (:class:`BetaSchedule`); the
signals by name in :mod:`~imssr.intrinsic.registry`.

Each signal is two modules: ``<name>_spec.py`` (its settings, rules and preset rows; no torch), which the config
reads, and its torch module, which the agent builds.  Importing this package imports no torch: the torch classes and
functions load on first use.
"""
import importlib

from imssr.intrinsic.registry import INTRINSIC_SIGNALS, SIGNAL_PLUGINS, make_signal

_LAZY = {"IntrinsicSignal": "base", "SSLSignal": "ssl", "RND": "rnd", "RE3": "re3", "BetaSchedule": "reward",
         "IntrinsicReward": "reward", "normalize": "reward"}
"""Name -> the module of this package that defines it."""

__all__ = ["BetaSchedule", "IntrinsicReward", "IntrinsicSignal", "SSLSignal", "RND", "RE3", "INTRINSIC_SIGNALS",
           "SIGNAL_PLUGINS", "make_signal", "normalize"]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'imssr.intrinsic' has no attribute {name!r}")
