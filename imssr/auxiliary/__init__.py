"""Auxiliary self-supervised tasks, one module each, registered by name (:mod:`~imssr.auxiliary.registry`)."""
from imssr.auxiliary.base import AuxiliaryTask, SharedNetworks
from imssr.auxiliary.curl import CURL
from imssr.auxiliary.pad import PAD
from imssr.auxiliary.registry import AUX_TASKS, make_aux
from imssr.auxiliary.soda import SODA
from imssr.auxiliary.svea import SVEA

__all__ = ["AuxiliaryTask", "SharedNetworks", "CURL", "SODA", "PAD", "SVEA", "AUX_TASKS", "make_aux"]
