"""One checkpoint: what it holds (:class:`Checkpoint`), its sealed, atomic write and its
verified, safe load.

A checkpoint holds the agent, optimisers, RNG states, counters, config, and the name of the
replay file that goes with it.  Where the files of a run lie, which one to resume or evaluate,
and the order in which a save writes and removes them (the replay files with it) is
:class:`imssr.rundir.RunDir`'s.

Checksums: every checkpoint carries the sha256 of its own bytes in its zip comment
(:mod:`imssr.integrity`), written with the file in the same rename, so a kill never separates
a file from its checksum.  Loading verifies it before torch reads a byte: a mismatch, or a file
cut short or extended past its checksum, is a :class:`CheckpointDamaged` error that names the
file, and so is a file without a checksum, which imssr did not write.

Every checkpoint is read with ``torch.load(weights_only=True)``: tensors and plain Python values
only (RNG states are stored as such).  A file that needs any other object (``os.system``, a
class of its own) is refused in one line before anything in it runs: "PATH is not an imssr
checkpoint: it contains objects of type os.system".

A full disk during a write is one "no space left on DEVICE while writing PATH" error; the file
that was there is untouched (the temporary file is removed).
"""
from __future__ import annotations

import os
import pickle
import shutil
import zipfile
from dataclasses import dataclass, field, fields
from typing import Any, Optional

import numpy as np
import torch

from imssr.errors import ImssrError
from imssr.files import atomic_path
from imssr.integrity import DISPLACED, MISMATCH, UNSEALED, HashingWriter, seal_zip, zip_seal_problem

FORMAT_VERSION = 1


class CheckpointDamaged(ImssrError):
    """A checkpoint file that exists but cannot be trusted: checksum mismatch or unreadable.

    ``reason`` is the short cause, e.g. "checksum mismatch"."""

    def __init__(self, message: str, path: str, reason: str):
        super().__init__(message)
        self.path, self.reason = path, reason


@dataclass(kw_only=True)
class Checkpoint:
    """What one checkpoint file holds: a training's whole state at an agent step, from which a
    resume continues as the uninterrupted run would (:mod:`imssr.training.checkpointing` makes
    and restores it).  In the file it is a dict of these names, in this order, and
    ``format_version``; tensors and plain Python values only."""

    config: dict
    """The run's config (:meth:`RunConfig.to_dict`), as it trained."""
    frame: int
    """Environment frames so far."""
    step: int
    """Agent steps so far."""
    episode: int
    """Training episodes finished."""
    next_eval_step: Optional[int]
    """The agent step at or after which the next periodic evaluation is due (None: none)."""
    next_ckpt_step: Optional[int]
    """The agent step at or after which the next periodic checkpoint is due (None: none)."""
    last_eval_step: int
    """The agent step of the last evaluation (-1: none yet)."""
    learning_starts: Optional[int] = None
    """Agent step from which the agent acts and learns; None where a file does not hold it: the
    seed phase's end."""
    eval_history: list = field(default_factory=list)
    """Every evaluation's ``eval.csv`` row and episode returns (``{"row", "returns"}``)."""
    action_rng: dict
    """The seed-phase actions' generator (numpy bit-generator state)."""
    agent: dict
    """The agent's networks, optimisers and generators (``SACAgent.state_dict``)."""
    env_rng: dict
    """The training env's generators."""
    eval_env_rngs: dict
    """Each evaluated scene's env generators, by scene."""
    global_rng: dict
    """Python's, numpy's and torch's global generators (:func:`imssr.rng.rng_states`)."""
    replay_file: Optional[str] = None
    """The replay buffer's index file in ``checkpoints/`` saved with it (None: none saved)."""
    replay_state: Optional[dict] = None
    """The replay buffer's head and its sampler's generator."""
    torch_threads: Optional[int] = None
    """torch's intra-op threads when it was saved (a CPU resume with another count drifts)."""
    episode_state: Optional[dict] = None
    """The episode open when it was saved (a stop in its middle), which a resume steps through
    again; None at an episode end."""
    burst_state: Optional[dict] = None
    """The burst of updates a stop interrupted (``updates_done``, the step's ``action``)."""
    before_final_eval: Optional[dict] = None
    """The evaluation state from before the off-schedule evaluation where the budget ran out."""

    def to_state(self) -> dict[str, Any]:
        """The dict the file holds (without ``format_version``)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_state(cls, state: dict[str, Any], path: str) -> "Checkpoint":
        """The checkpoint of a loaded file's dict; one that lacks a field it needs is
        :class:`CheckpointDamaged`."""
        names = {f.name for f in fields(cls)}
        values = {k: v for k, v in state.items() if k in names}
        # Files from before per-scene evaluation envs hold the one scene's generators.
        if values.get("eval_env_rngs") is None and "eval_env_rng" in state:
            env = (state.get("config") or {}).get("env") if isinstance(state.get("config"), dict) else None
            mode = env.get("mode", "training") if isinstance(env, dict) else "training"
            values["eval_env_rngs"] = {mode: state["eval_env_rng"]}
        try:
            return cls(**values)
        except TypeError:
            missing = sorted(f.name for f in fields(cls) if f.name not in values)
            raise CheckpointDamaged(f"{path} is not a whole imssr checkpoint: it holds no {', '.join(missing)}",
                                    path, "not an imssr checkpoint") from None

    def run_config(self):
        """The run's config as it trained (:class:`~imssr.config.RunConfig`)."""
        from imssr.config import RunConfig

        return RunConfig.from_dict(self.config)


def write_checkpoint(path: str, ckpt: Checkpoint) -> str:
    """Write ``ckpt`` (with :data:`FORMAT_VERSION`) to ``path``, sealed and atomically."""
    state = dict(ckpt.to_state(), format_version=FORMAT_VERSION)
    with atomic_path(path, needed=_nbytes(state)) as tmp:
        _write_sealed(state, tmp)
    return path


def copy_checkpoint(src: str, dst: str) -> str:
    """A real copy of the checkpoint file ``src`` at ``dst``, written atomically (the seal is in
    the bytes, so the copy verifies on its own)."""
    with atomic_path(dst, needed=os.path.getsize(src)) as tmp:
        with open(src, "rb") as fin, open(tmp, "wb") as fout:
            shutil.copyfileobj(fin, fout, 1 << 22)
    return dst


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


def load_checkpoint(path: str) -> Checkpoint:
    """Load and verify a checkpoint; :class:`CheckpointDamaged` when it cannot be trusted."""
    if not os.path.exists(path):
        raise ImssrError(f"checkpoint not found: {path}")
    try:
        problem = zip_seal_problem(path)
        starts_as_zip = _starts_as_zip(path)
    except OSError as exc:
        raise CheckpointDamaged(f"cannot read checkpoint {path}: {exc.strerror or exc}", path,
                                f"unreadable: {exc.strerror or exc}") from None
    if problem in (MISMATCH, DISPLACED):
        raise CheckpointDamaged(f"checkpoint {path} is damaged ({problem})", path, problem)
    if not starts_as_zip:
        # torch reads a file that does not start as a zip archive in its legacy pickle format,
        # also one with a zip archive (and a seal) behind its pickle: never an imssr checkpoint.
        raise CheckpointDamaged(f"{path} is not an imssr checkpoint (not a torch checkpoint file)", path,
                                "not an imssr checkpoint")
    if not zipfile.is_zipfile(path):
        raise CheckpointDamaged(f"corrupt checkpoint {path}: cut short (its zip directory is missing)", path,
                                "unreadable: cut short")
    if problem == UNSEALED:
        # imssr seals every checkpoint it writes: this one comes from elsewhere.  Listing what its
        # pickle would import runs none of it.
        foreign = _foreign_globals(path)
        what = f"it contains objects of type {', '.join(foreign)}" if foreign else "it carries no imssr checksum"
        raise CheckpointDamaged(f"{path} is not an imssr checkpoint: {what}", path, "not an imssr checkpoint")
    try:
        # Never unpickle arbitrary objects: a checkpoint from a shared file system could run code.
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        # The bytes are as sealed, so this is a file imssr did not write, not a damaged one.
        foreign = _foreign_globals(path)
        what = (f"it contains objects of type {', '.join(foreign)}" if foreign else
                f"a weights-only load refuses it ({_unpickler_reason(exc)})")
        raise CheckpointDamaged(f"{path} is not an imssr checkpoint: {what}", path, "not an imssr checkpoint") from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CheckpointDamaged(f"corrupt checkpoint {path}: {first}", path, f"unreadable: {first}") from None
    except (KeyError, IndexError, TypeError, AttributeError) as exc:
        # A zip archive whose pickle is damaged: the unpickler fails where it trips ("KeyError: 101").
        first = f"{type(exc).__name__}: {exc}".splitlines()[0]
        raise CheckpointDamaged(f"corrupt checkpoint {path}: {first}", path, f"unreadable: {first}") from None
    if not isinstance(state, dict) or state.get("format_version") != FORMAT_VERSION:
        raise CheckpointDamaged(f"{path} is not an imssr checkpoint of format {FORMAT_VERSION}", path,
                                "not an imssr checkpoint")
    return Checkpoint.from_state(state, path)


def _unpickler_reason(exc: pickle.UnpicklingError) -> str:
    """What torch's weights-only unpickler objected to (its "WeightsUnpickler error: ..." line),
    without the advice around it to load the file with ``weights_only=False``."""
    _, marker, rest = str(exc).partition("WeightsUnpickler error:")
    reason = next((line.strip() for line in rest.splitlines() if line.strip()), "") if marker else ""
    return reason or type(exc).__name__


def _starts_as_zip(path: str) -> bool:
    """Whether ``path`` begins as a zip archive does (a checkpoint cut short keeps its start)."""
    with open(path, "rb") as fh:
        return fh.read(4) == b"PK\x03\x04"


def _foreign_globals(path: str) -> list[str]:
    """The globals (``module.name``) a checkpoint file needs beyond what :func:`load_checkpoint`
    allows, as the user knows them (``posix.system`` is ``os.system``)."""
    try:
        names = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:  # noqa: BLE001 - a file too damaged to list: reported as corrupt instead
        return []
    shown = []
    for name in names:
        module, _, attr = name.rpartition(".")
        shown.append(f"os.{attr}" if module in ("posix", "nt") else name)
    return sorted(set(shown))
