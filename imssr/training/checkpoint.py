"""Atomic checkpoints: everything needed to continue a run bit for bit.

Layout under ``RUN/checkpoints/``: ``latest.pt`` (agent, optimisers, RNG
states, counters, config) and ``replay-<step>.npz`` (the buffer, optional).
The buffer is written first and the checkpoint names it, so a kill at any
moment leaves a consistent pair.
"""
from __future__ import annotations

import glob
import os
import pickle
import zipfile
from typing import Any

import torch

from imssr.errors import ImssrError
from imssr.utils import atomic_path

FORMAT_VERSION = 1


def checkpoint_dir(run_dir: str) -> str:
    return os.path.join(run_dir, "checkpoints")


def latest_path(run_dir: str) -> str:
    return os.path.join(checkpoint_dir(run_dir), "latest.pt")


def save_checkpoint(run_dir: str, state: dict[str, Any], keep: int = 1) -> str:
    state = dict(state, format_version=FORMAT_VERSION)
    path = latest_path(run_dir)
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    if keep > 0:
        # A hard link costs no second write of the same bytes.
        numbered = os.path.join(checkpoint_dir(run_dir), f"step-{state['step']:09d}.pt")
        if os.path.exists(numbered):
            os.unlink(numbered)
        os.link(path, numbered)
        for old in sorted(glob.glob(os.path.join(checkpoint_dir(run_dir), "step-*.pt")))[:-keep]:
            os.unlink(old)
    # Replay files not named by the newest checkpoint are stale (numbered
    # checkpoints therefore hold weights for evaluation; exact resume uses latest),
    # and so are temporary files left by a process killed mid-write.
    current = state.get("replay_file")
    keep_files = {current, f"{current}.frames.npy"} if current else set()
    for old in glob.glob(os.path.join(checkpoint_dir(run_dir), "replay-*")):
        if os.path.basename(old) not in keep_files:
            os.unlink(old)
    for tmp in glob.glob(os.path.join(checkpoint_dir(run_dir), ".tmp-*")):
        os.unlink(tmp)
    return path


def load_checkpoint(path: str) -> dict[str, Any]:
    if not os.path.exists(path):
        raise ImssrError(f"checkpoint not found: {path}")
    try:
        # Our own files hold numpy RNG states, which weights_only refuses.
        state = torch.load(path, map_location="cpu", weights_only=False)
    except (RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile, ValueError, OSError) as exc:
        raise ImssrError(f"corrupt checkpoint {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    if not isinstance(state, dict) or state.get("format_version") != FORMAT_VERSION:
        raise ImssrError(f"{path} is not an imssr checkpoint of format {FORMAT_VERSION}")
    return state
