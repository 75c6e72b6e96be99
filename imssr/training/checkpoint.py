"""Atomic, checksummed checkpoints: everything needed to continue a run bit for bit.

Layout under ``RUN/checkpoints/``:

* ``latest.pt``: agent, optimisers, RNG states, counters, config, and the name of the replay
  file that goes with it;
* ``step-<step>.pt``: the ``train.keep_checkpoints`` newest checkpoints, real copies (see
  :func:`save_checkpoint`), for ``imssr evaluate --checkpoint`` and as fallbacks;
* ``replay-<step>.npz`` and ``replay-<step>.npz.frames.npy``: the replay buffer of ``latest.pt``
  (and of the newest ``step-*.pt``, which holds the same step).

Order of writes, each atomic (temporary file, fsync, rename): the replay frames, the replay
``.npz`` (which holds the frames' sha256), ``latest.pt`` (which names the ``.npz``), its numbered
copy, then removal of what the new ``latest.pt`` no longer names.  A kill at any moment leaves
``latest.pt`` old or new, whole, with the replay files it names.

Checksums: every checkpoint and replay ``.npz`` carries the sha256 of its own bytes in its zip
comment (:mod:`imssr.integrity`), written with the file in the same rename, so a kill never
separates a file from its checksum.  Loading verifies it; a mismatch is a
:class:`CheckpointDamaged` error that names the file.  ``--resume`` on a damaged ``latest.pt``
falls back to the newest numbered checkpoint that verifies (:func:`usable_checkpoint`).
Checkpoints written before checksums (no seal) load unverified.

Every checkpoint is read with ``torch.load(weights_only=True)``: tensors and plain Python values
only (RNG states are stored as such), plus the numpy types of the RNG states that older files
hold.  A file that needs any other object (``os.system``, a class of its own) is refused in one
line before anything in it runs: "PATH is not an imssr checkpoint: it contains objects of type
os.system".

A full disk during any of these writes is one "no space left on DEVICE while writing PATH"
error; the files of the previous checkpoint are untouched (temporary files are removed).
"""
from __future__ import annotations

import glob
import os
import pickle
import shutil
import zipfile
from typing import Any, Optional

import numpy as np
import torch

from imssr.errors import ImssrError
from imssr.integrity import HashingWriter, check_zip, seal_zip
from imssr.utils import atomic_path

FORMAT_VERSION = 1


def checkpoint_dir(run_dir: str) -> str:
    return os.path.join(run_dir, "checkpoints")


def latest_path(run_dir: str) -> str:
    return os.path.join(checkpoint_dir(run_dir), "latest.pt")


class CheckpointDamaged(ImssrError):
    """A checkpoint file that exists but cannot be trusted: checksum mismatch or unreadable.

    ``reason`` is the short cause, e.g. "checksum mismatch"."""

    def __init__(self, message: str, path: str, reason: str):
        super().__init__(message)
        self.path, self.reason = path, reason


def numbered_path(run_dir: str, step: int) -> str:
    return os.path.join(checkpoint_dir(run_dir), f"step-{step:09d}.pt")


def numbered_checkpoints(run_dir: str) -> list[str]:
    """The retained ``step-*.pt`` files, oldest first."""
    return sorted(glob.glob(os.path.join(checkpoint_dir(run_dir), "step-*.pt")))


def save_checkpoint(run_dir: str, state: dict[str, Any], keep: int = 1) -> str:
    state = dict(state, format_version=FORMAT_VERSION)
    path = latest_path(run_dir)
    with atomic_path(path, needed=_nbytes(state)) as tmp:
        _write_sealed(state, tmp)
    if keep > 0:
        # Real copies, not hard links of latest.pt (as before) nor a latest that points at a
        # numbered file: a damaged byte then spoils one file, not both, and the newest copy
        # holds latest's own step, so a resume that falls back to it still finds its replay
        # file and stays exact.  The price is one more write of the weights; the replay
        # buffer, the large part, is written once.
        numbered = numbered_path(run_dir, state["step"])
        with atomic_path(numbered, needed=os.path.getsize(path)) as tmp:
            with open(path, "rb") as src, open(tmp, "wb") as dst:
                shutil.copyfileobj(src, dst, 1 << 22)
        for old in numbered_checkpoints(run_dir)[:-keep]:
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


def _write_sealed(state: dict, path: str) -> None:
    with open(path, "wb") as fh:
        # Through a Python file object: torch writing to a path turns a full disk into a
        # C++ "iostream error"; here the writer keeps the OSError.
        writer = HashingWriter(fh, hashing=False)
        try:
            torch.save(state, writer)
        except RuntimeError:
            if writer.error is not None:
                raise writer.error from None
            raise
    seal_zip(path)  # hashes the bytes as they are on disk


def _nbytes(obj) -> int:
    """Bytes of the tensors and arrays in ``obj`` (the bulk of a checkpoint)."""
    if isinstance(obj, torch.Tensor):
        return obj.element_size() * obj.nelement()
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, dict):
        return sum(_nbytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(_nbytes(v) for v in obj)
    return 0


def load_checkpoint(path: str) -> dict[str, Any]:
    """Load and verify a checkpoint; :class:`CheckpointDamaged` when it cannot be trusted."""
    if not os.path.exists(path):
        raise ImssrError(f"checkpoint not found: {path}")
    try:
        intact = check_zip(path)
    except OSError as exc:
        raise CheckpointDamaged(f"cannot read checkpoint {path}: {exc.strerror or exc}", path,
                                f"unreadable: {exc.strerror or exc}") from None
    if intact is False:
        raise CheckpointDamaged(f"checkpoint {path} is damaged (checksum mismatch)", path, "checksum mismatch")
    try:
        # Never unpickle arbitrary objects: a checkpoint from a shared file system could run
        # code.  The numpy types allowed here are the legacy RNG states of older files only.
        with torch.serialization.safe_globals(_LEGACY_NUMPY_GLOBALS):
            state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        foreign = _foreign_globals(path)
        if foreign:
            raise CheckpointDamaged(f"{path} is not an imssr checkpoint: it contains objects of type "
                                    f"{', '.join(foreign)}", path, "not an imssr checkpoint") from None
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CheckpointDamaged(f"corrupt checkpoint {path}: {first}", path, f"unreadable: {first}") from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CheckpointDamaged(f"corrupt checkpoint {path}: {first}", path, f"unreadable: {first}") from None
    if not isinstance(state, dict) or state.get("format_version") != FORMAT_VERSION:
        raise CheckpointDamaged(f"{path} is not an imssr checkpoint of format {FORMAT_VERSION}", path,
                                "not an imssr checkpoint")
    return state


# What pickles a numpy RNG state of the legacy form ("MT19937", uint32 key array, ...), which
# checkpoints of imssr 0.x hold; current files store it as plain values (imssr.utils.rng_states).
_RECONSTRUCT = np.zeros(1).__reduce__()[0]  # numpy._core.multiarray._reconstruct (numpy 2)
_LEGACY_NUMPY_GLOBALS = [_RECONSTRUCT, (_RECONSTRUCT, "numpy.core.multiarray._reconstruct"),  # numpy 1's name
                         np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def _foreign_globals(path: str) -> list[str]:
    """The globals (``module.name``) a checkpoint file needs beyond what :func:`load_checkpoint`
    allows, as the user knows them (``posix.system`` is ``os.system``)."""
    try:
        names = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:  # noqa: BLE001 - a file too damaged to list: reported as corrupt instead
        return []
    allowed = {g[1] if isinstance(g, tuple) else f"{g.__module__}.{g.__qualname__}" for g in _LEGACY_NUMPY_GLOBALS}
    shown = []
    for name in names:
        if name in allowed:
            continue
        module, _, attr = name.rpartition(".")
        shown.append(f"os.{attr}" if module in ("posix", "nt") else name)
    return sorted(set(shown))


def usable_checkpoint(run_dir: str, verb: str = "resuming from") -> tuple[dict[str, Any], str, Optional[str]]:
    """The run's checkpoint to continue from: ``(state, path, note)``.

    ``latest.pt`` when it verifies (``note`` is None); otherwise the newest retained
    ``step-*.pt`` that does, with a one-line ``note`` that says so, e.g. "latest.pt is damaged
    (checksum mismatch); resuming from step-000000250.pt at agent step 250".
    """
    latest = latest_path(run_dir)
    numbered = numbered_checkpoints(run_dir)
    if not os.path.exists(latest):
        if not numbered:
            raise ImssrError(f"nothing to resume: {latest} does not exist" if verb == "resuming from"
                             else f"checkpoint not found: {latest}")
        problem, error = "missing", f"{latest} is missing"
    else:
        try:
            return load_checkpoint(latest), latest, None
        except CheckpointDamaged as exc:
            problem, error = f"damaged ({exc.reason})", str(exc)
            if not numbered:
                raise
    for path in reversed(numbered):
        try:
            state = load_checkpoint(path)
        except CheckpointDamaged:
            continue
        note = (f"{os.path.basename(latest)} is {problem}; {verb} {os.path.basename(path)} "
                f"at agent step {state['step']}")
        return state, path, note
    raise ImssrError(f"{error}, and no retained step-*.pt checkpoint in {checkpoint_dir(run_dir)} is valid")


def run_checkpoint(run_dir: str, spec: Optional[str] = None,
                   verb: str = "evaluating") -> tuple[dict[str, Any], Optional[str]]:
    """The checkpoint of a trained run that ``--checkpoint`` chooses: ``(state, note)``.

    ``spec`` is read by :func:`select_checkpoint` (a file, or the agent step of a retained
    ``step-*.pt``); None takes the latest that verifies, with a ``note`` when that is not
    ``latest.pt`` (:func:`usable_checkpoint`)."""
    if spec:
        return load_checkpoint(select_checkpoint(run_dir, spec)), None
    state, _, note = usable_checkpoint(run_dir, verb=verb)
    return state, note


def select_checkpoint(run_dir: str, spec: str) -> str:
    """The checkpoint file named by ``spec``: a path (absolute, relative, or inside the run's
    ``checkpoints/``), or an agent step of a retained ``step-*.pt``."""
    if spec.strip().isdigit():
        path = numbered_path(run_dir, int(spec))
        if os.path.exists(path):
            return path
        steps = [str(int(os.path.basename(p)[5:-3])) for p in numbered_checkpoints(run_dir)
                 if os.path.basename(p)[5:-3].isdigit()]
        raise ImssrError(f"no checkpoint at agent step {int(spec)} in {checkpoint_dir(run_dir)}; "
                         f"retained steps: {', '.join(steps) if steps else 'none'} (or give a file)")
    for path in (spec, os.path.join(checkpoint_dir(run_dir), spec)):
        if os.path.isfile(path):
            return path
    raise ImssrError(f"checkpoint not found: {spec}")
