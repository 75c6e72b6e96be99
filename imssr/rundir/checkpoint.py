"""A run's checkpoints: what one holds (:class:`Checkpoint`), its sealed, atomic write and its
verified, safe load, and :class:`Checkpoints`: which there are in a run, the save of one
(``latest.pt``, its numbered copies and the replay files it names), and which one a command
continues from or loads.

A checkpoint holds the agent, optimisers, RNG states, counters, config, and the name of the
replay file that goes with it.  Order of a save's writes, each atomic (temporary file, fsync,
rename): the frames written since the last checkpoint (one new frame file), the replay ``.npz``
(which names the frame files that hold live frames, with their sha256), ``latest.pt`` (which
names the ``.npz``), its numbered copy, then removal of what the new ``latest.pt`` no longer
names.  A kill at any moment leaves ``latest.pt`` old or new, whole, with the replay files it
names; a damaged ``latest.pt`` falls back to the newest numbered checkpoint that verifies.

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
that was there is untouched (the temporary file is removed).  torch, which reads and writes
checkpoints, is loaded only where one is: a run's layout, logs and status need none.
"""
from __future__ import annotations

import glob
import os
import pickle
import shutil
import zipfile
from dataclasses import dataclass, field, fields
from typing import Any, NamedTuple, Optional

from imssr.errors import ImssrError
from imssr.files import TEMP_GLOB, atomic_path
from imssr.integrity import DISPLACED, MISMATCH, UNSEALED, HashingWriter, seal_zip, zip_seal_problem
from imssr.rundir.layout import CHECKPOINT_GLOB, REPLAY_GLOB, RunLayout

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
    def from_state(cls, state: dict[str, Any], path: str) -> Checkpoint:
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
    import torch

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
    if isinstance(obj, dict):
        return sum(_nbytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(_nbytes(v) for v in obj)
    nbytes = getattr(obj, "nbytes", 0)  # a tensor's or an array's
    return nbytes if isinstance(nbytes, int) else 0


def load_checkpoint(path: str) -> Checkpoint:
    """Load and verify a checkpoint; :class:`CheckpointDamaged` when it cannot be trusted."""
    import torch

    if not os.path.exists(path):
        raise ImssrError(f"checkpoint not found: {path}")
    try:
        problem = zip_seal_problem(path)
        with open(path, "rb") as fh:
            starts_as_zip = fh.read(4) == b"PK\x03\x04"  # a checkpoint cut short keeps its start
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
        # imssr seals every checkpoint it writes: this one comes from elsewhere.
        raise _not_ours(path, "it carries no imssr checksum")
    try:
        # Never unpickle arbitrary objects: a checkpoint from a shared file system could run code.
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        # The bytes are as sealed, so this is a file imssr did not write, not a damaged one.
        raise _not_ours(path, f"a weights-only load refuses it ({_unpickler_reason(exc)})") from None
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


def _not_ours(path: str, otherwise: str) -> CheckpointDamaged:
    """The error for a file imssr did not write: it names the globals (``module.name``) its pickle
    needs beyond what :func:`load_checkpoint` allows, as the user knows them (``posix.system`` is
    ``os.system``), or says ``otherwise`` when it needs none.  Listing them runs none of them."""
    import torch

    try:
        names = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:  # noqa: BLE001 - a file too damaged to list: reported as corrupt instead
        names = []
    shown = set()
    for name in names:
        module, _, attr = name.rpartition(".")
        shown.add(f"os.{attr}" if module in ("posix", "nt") else name)
    what = f"it contains objects of type {', '.join(sorted(shown))}" if shown else otherwise
    return CheckpointDamaged(f"{path} is not an imssr checkpoint: {what}", path, "not an imssr checkpoint")


class CheckpointFile(NamedTuple):
    """A checkpoint file as found and loaded (:meth:`RunDir.checkpoint`)."""

    checkpoint: Checkpoint
    """What it holds: the config, the agent, the loop's state and every generator."""
    path: str
    """The file it was loaded from."""
    note: Optional[str]
    """Why it is not ``latest.pt`` when it fell back to another (None otherwise)."""


class Checkpoints(RunLayout):
    """The run's checkpoint files and the replay files they name (a part of
    :class:`~imssr.rundir.RunDir`)."""

    def has_latest(self) -> bool:
        """Whether ``latest.pt`` exists."""
        return os.path.exists(self.latest)

    def has_checkpoint(self) -> bool:
        """Something ``imssr train --resume`` continues from: ``latest.pt`` or a retained
        ``step-*.pt`` (the resume falls back to those when ``latest.pt`` is missing or damaged)."""
        return self.has_latest() or bool(self.numbered_checkpoints())

    def numbered_checkpoints(self) -> list[str]:
        """The retained ``step-*.pt`` files, oldest first."""
        return sorted(glob.glob(os.path.join(self.checkpoint_dir, CHECKPOINT_GLOB)))

    def checkpoint_steps(self) -> list[int]:
        """The agent steps of the retained ``step-*.pt`` files, oldest first."""
        digits = [os.path.basename(path)[len("step-"):-len(".pt")] for path in self.numbered_checkpoints()]
        return [int(d) for d in digits if d.isdigit()]

    def save_checkpoint(self, ckpt: Checkpoint, keep: int = 1, replay=None) -> str:
        """Write ``ckpt`` as ``latest.pt`` and its numbered copy (``keep`` > 0: the ``keep``
        newest copies stay), after the replay buffer ``replay`` when ``ckpt`` names a replay file
        (only the frames that arrived since the previous save are new files); then remove the
        replay files ``latest.pt`` no longer names and the temporary files of a process killed
        mid-write.  A save that fails (a full disk) leaves the previous ``latest.pt`` as it was and
        removes the replay files it wrote, which no checkpoint names.  Returns ``latest.pt``'s path."""
        before, replay_before = _identity(self.latest), self._all_replay_files()
        try:
            self.write_replay(ckpt, replay)
            path = write_checkpoint(self.latest, ckpt)
            if keep > 0:
                # Real copies, not links to latest.pt: a damaged byte spoils one file, not both, and
                # the newest copy holds latest's own step, so a resume that falls back to it still
                # finds its replay file and stays exact.  The price is one more write of the weights;
                # the replay buffer, the large part, is written once.
                copy_checkpoint(path, self.numbered(ckpt.step))
                for old in self.numbered_checkpoints()[:-keep]:
                    os.unlink(old)
        except ImssrError:
            if ckpt.replay_file and _identity(self.latest) == before:
                # latest.pt is the previous one: drop what this save wrote, which nothing names.
                for new in self._all_replay_files() - replay_before:
                    os.unlink(new)
            raise
        # Numbered checkpoints therefore hold weights for evaluation; exact resume uses latest.
        self._remove_unneeded(ckpt.replay_file)
        return path

    def _remove_unneeded(self, replay_file: Optional[str]) -> None:
        """Remove the replay files other than those of ``replay_file`` (what ``latest.pt`` names)
        and the temporary files of a process killed mid-write."""
        self.remove_unnamed_replay_files(replay_file)
        for tmp in glob.glob(os.path.join(self.checkpoint_dir, TEMP_GLOB)):
            os.unlink(tmp)

    def checkpoint(self, spec: Optional[str] = None, verb: str = "resuming from") -> CheckpointFile:
        """The checkpoint a command continues from or loads: ``(checkpoint, path, note)``.  The one rule
        for every command (``imssr train --resume``, ``evaluate``, ``analyze``, ``imssr.load_run``):

        - ``spec`` None: ``latest.pt`` when it verifies (``note`` None); else, when it is missing
          or damaged, the newest retained ``step-*.pt`` that verifies, with a one-line ``note``
          that says so in the words of ``verb``, e.g. "latest.pt is damaged (checksum mismatch);
          resuming from step-000000250.pt at agent step 250".
        - ``spec`` an agent step (digits): the retained ``step-<spec>.pt``.
        - ``spec`` a file: that path (absolute or relative), or that name inside ``checkpoints/``.

        A checkpoint named by ``spec`` is loaded as it is, with no fall-back; when it is one of the
        run's own and cannot be trusted, the error names the newest retained ``step-*.pt`` that
        verifies and how to choose it ("--checkpoint 250").  Every load verifies the file
        (:func:`~imssr.rundir.checkpoint.load_checkpoint`); none of them is a one-line error.
        """
        if spec:
            path = self._named_checkpoint(str(spec))
            try:
                return CheckpointFile(load_checkpoint(path), path, None)
            except CheckpointDamaged as exc:
                if os.path.dirname(os.path.abspath(path)) != os.path.abspath(self.checkpoint_dir):
                    raise
                other = self._newest_valid(exclude=path)
                if other is None:
                    raise
                raise CheckpointDamaged(f"{exc}; {os.path.basename(other.path)} verifies (agent step "
                                        f"{other.checkpoint.step}: --checkpoint {other.checkpoint.step})",
                                        exc.path, exc.reason) from None
        latest = self.latest
        numbered = self.numbered_checkpoints()
        if not os.path.exists(latest):
            if not numbered:
                raise ImssrError(f"nothing to resume: {latest} does not exist" if verb == "resuming from"
                                 else f"checkpoint not found: {latest}")
            problem, error = "missing", f"{latest} is missing"
        else:
            try:
                return CheckpointFile(load_checkpoint(latest), latest, None)
            except CheckpointDamaged as exc:
                problem, error = f"damaged ({exc.reason})", str(exc)
                if not numbered:
                    raise
        found = self._newest_valid()
        if found is None:
            raise ImssrError(f"{error}, and no retained step-*.pt checkpoint in {self.checkpoint_dir} is valid")
        note = (f"{os.path.basename(latest)} is {problem}; {verb} {os.path.basename(found.path)} "
                f"at agent step {found.checkpoint.step}")
        return found._replace(note=note)

    def _newest_valid(self, exclude: Optional[str] = None) -> Optional[CheckpointFile]:
        """The newest retained ``step-*.pt`` (other than ``exclude``) that verifies, or None."""
        for path in reversed(self.numbered_checkpoints()):
            if exclude is not None and os.path.abspath(path) == os.path.abspath(exclude):
                continue
            try:
                return CheckpointFile(load_checkpoint(path), path, None)
            except CheckpointDamaged:
                continue
        return None

    def _named_checkpoint(self, spec: str) -> str:
        """The checkpoint file ``spec`` names (see :meth:`checkpoint`)."""
        if spec.strip().isdigit():
            path = self.numbered(int(spec))
            if os.path.exists(path):
                return path
            steps = self.checkpoint_steps()
            raise ImssrError(f"no checkpoint at agent step {int(spec)} in {self.checkpoint_dir}; "
                             f"retained steps: {', '.join(map(str, steps)) if steps else 'none'} (or give a file)")
        for path in (spec, os.path.join(self.checkpoint_dir, spec)):
            if os.path.isfile(path):
                return path
        raise ImssrError(f"checkpoint not found: {spec}")

    # -- the replay files a checkpoint names ----------------------------------------------
    def replay_files(self, name: str) -> list[str]:
        """The files of the replay buffer ``name``: its ``.npz`` index and the frame files it names;
        :class:`~imssr.replay.buffer.ReplayFileError` when the index cannot be read and verified."""
        from imssr.replay import buffer as replay_buffer

        return replay_buffer.replay_files(self.replay_path(name))

    def write_replay(self, ckpt: Checkpoint, replay) -> None:
        """Save the replay buffer ``replay`` as the replay file ``ckpt`` names (when it names one):
        only the frames that arrived since its previous save are new files."""
        if ckpt.replay_file:
            if replay is None:
                raise ValueError("a checkpoint that names a replay file is saved with its replay buffer")
            replay.save(self.replay_path(ckpt.replay_file))

    def _all_replay_files(self) -> set[str]:
        return set(glob.glob(os.path.join(self.checkpoint_dir, REPLAY_GLOB)))

    def remove_unnamed_replay_files(self, name: Optional[str]) -> None:
        """Remove the replay files that the replay buffer ``name`` (None: none) does not use.  When
        the index ``name`` cannot be read and verified, what is live is unknown: nothing is removed,
        and a one-line warning says so (the next save cleans up)."""
        from imssr.replay.buffer import ReplayFileError

        kept: set[str] = set()
        if name:
            try:
                kept = {os.path.basename(p) for p in self.replay_files(name)}
            except ReplayFileError as exc:
                print(f"imssr: warning: {exc}; no replay file is removed", flush=True)
                return
        for old in self._all_replay_files():
            if os.path.basename(old) not in kept:
                os.unlink(old)

    def _replay_kept(self, name: str) -> bool:
        """Whether the files of the replay buffer ``name`` are there: false when its index is
        missing or a file it names is; true when its index cannot be read (that is its error)."""
        from imssr.replay.buffer import ReplayFileError

        if not os.path.exists(self.replay_path(name)):
            return False
        try:
            return all(os.path.exists(p) for p in self.replay_files(name))
        except ReplayFileError:
            return True

    def load_replay(self, found: CheckpointFile, replay, refill: bool = False) -> Optional[str]:
        """Load into ``replay`` (a replay buffer) the replay files the checkpoint ``found`` names;
        returns why the buffer must be refilled instead (None when it loaded).  A missing or
        damaged buffer is a one-line error, or (``refill``) a reason; an older checkpoint that
        ``checkpoint()`` fell back to has none kept, and says so."""
        from imssr.replay.buffer import ReplayFileError

        ckpt = found.checkpoint
        if not ckpt.replay_file:
            return "checkpoint holds no replay buffer"
        path = self.replay_path(ckpt.replay_file)
        try:
            replay.load(path, ckpt.replay_state["rng"])
        except ReplayFileError as exc:
            # Only latest.pt's replay buffer is kept: an older checkpoint resumes without one.
            if found.path != self.latest and not self._replay_kept(ckpt.replay_file):
                return f"no replay buffer was kept for {os.path.basename(found.path)}"
            if refill:
                return str(exc)
            raise ImssrError(f"{exc}; `imssr train --resume --refill-buffer` continues with an empty "
                             "buffer refilled by random actions (not an exact resume)") from None
        if replay.state_dict()["head"] != ckpt.replay_state["head"]:
            raise ImssrError(f"replay buffer {path} does not match the checkpoint")
        return None


def _identity(path: str) -> Optional[tuple]:
    """Which file ``path`` is now (None if none): tells whether a save replaced it."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size
