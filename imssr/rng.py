"""The global random number generators' state: seeding them, and their state in a checkpoint.

A checkpoint holds the Python, numpy and torch global RNG states (:func:`rng_states`) in types that
``torch.load(weights_only=True)`` reads, so that a resumed run draws what the uninterrupted one would have.  The
seed offsets of a run's streams are in :mod:`imssr.seeds`.
"""
from __future__ import annotations

import random

import numpy as np
import torch


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def rng_states() -> dict:
    """The global Python, numpy and torch RNG states, in types that ``torch.load(weights_only=True)``
    reads (plain containers and tensors): a checkpoint then never needs pickled numpy objects."""
    return {"python": random.getstate(), "numpy": random_state_to_plain(np.random.get_state()),
            "torch": torch.get_rng_state()}


def set_rng_states(states: dict) -> None:
    random.setstate(states["python"])
    np.random.set_state(random_state_from_plain(states["numpy"]))
    torch.set_rng_state(states["torch"])


def random_state_to_plain(state: tuple) -> dict:
    """A ``np.random.RandomState.get_state()`` tuple as a dict of plain values (the MT19937 key
    as a list of ints), so that a checkpoint holding it loads with ``weights_only=True``."""
    name, key, pos, has_gauss, gauss = state
    return {"bit_generator": str(name), "key": [int(k) for k in key], "pos": int(pos),
            "has_gauss": int(has_gauss), "gauss": float(gauss)}


def random_state_from_plain(state) -> tuple:
    """The ``RandomState.set_state`` tuple of :func:`random_state_to_plain`'s dict; a tuple (as
    checkpoints of imssr 0.x hold it) passes through."""
    if not isinstance(state, dict):
        return state
    return (state["bit_generator"], np.asarray(state["key"], dtype=np.uint32), state["pos"],
            state["has_gauss"], state["gauss"])
