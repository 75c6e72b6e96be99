"""A run directory: the one place that knows its layout and its life.

Layout of ``RUN/`` (every name below is a constant of this module)::

    config.json             the run's resolved config (what ``imssr train --config`` runs)
    provenance.json         which code and machine made it: a record per start and resume
    train.csv               one row per training episode
    eval.csv                one row per evaluation and scene during training
    eval_episodes.csv       one row per evaluation episode during training
    evaluate.csv            ``imssr evaluate``: one row per scene, appended
    evaluate_episodes.csv   ``imssr evaluate``: one row per episode, appended
    learning_curve.png      ``imssr plot`` / the end of ``imssr train``
    tb/                     TensorBoard events
    videos/                 evaluation videos
    montage.png             ``imssr evaluate --montage``
    episode.gif             ``imssr demo``: the trained policy
    analysis/               ``imssr analyze``
    wandb_run.json          the W&B run id a resume continues
    replay-frames.mmap      ``train.replay_device=disk``: the replay frames while a training runs
    status.json             how the last training of the run ended (see :meth:`RunDir.status`)
    done.json               ``imssr sweep``: the run reached its budget
    sweep.log               ``imssr sweep``: the output of every attempt
    .imssr.lock             held while a process writes the run (:mod:`imssr.rundir.lock`)
    checkpoints/
        latest.pt                      the checkpoint a resume continues from
        step-<step>.pt                 the ``train.keep_checkpoints`` newest, real copies
        replay-<step>.npz              the index of the replay buffer ``latest.pt`` names
        replay-frames-<a>-<b>.npy      its frames a to b-1 (:mod:`imssr.replay.buffer`)

Order of a checkpoint's writes, each atomic (temporary file, fsync, rename): the frames written
since the last checkpoint (one new frame file), the replay ``.npz`` (which names the frame files
that hold live frames, with their sha256), ``latest.pt`` (which names the ``.npz``), its numbered
copy, then removal of what the new ``latest.pt`` no longer names.  A kill at any moment leaves
``latest.pt`` old or new, whole, with the replay files it names; a damaged ``latest.pt`` falls
back to the newest numbered checkpoint that verifies.

Readers (``imssr evaluate``, ``analyze``, ``report``, :class:`imssr.api.Run`) take no lock:
every file they read is replaced atomically.
"""
from __future__ import annotations

import contextlib
import glob
import json
import os
import shutil
import time
from typing import TYPE_CHECKING, Callable, Iterable, Iterator, NamedTuple, Optional, Sequence, Union

from imssr.config import RunConfig, load_config
from imssr.errors import DivergedError, ImssrError
from imssr.files import OWN_FILE_RULE, TEMP_GLOB, atomic_write_text, read_csv
from imssr.jsonio import dumps
from imssr.rundir.lock import LOCK_FILE, DirectoryLock, held_by

if TYPE_CHECKING:  # torch's: imported where a checkpoint is read or written
    from imssr.rundir.checkpoint import Checkpoint

CONFIG_FILE = "config.json"
"""The run's resolved config: written before training starts, read by every command on the run."""
PROVENANCE_FILE = "provenance.json"
"""``{"records": [...]}``: :func:`imssr.provenance.record` of every start and resume, in order."""
TRAIN_LOG = "train.csv"
"""One row per training episode."""
EVAL_LOG = "eval.csv"
"""One row per evaluation and scene during training."""
EVAL_EPISODES_LOG = "eval_episodes.csv"
"""One row per episode of those evaluations."""
EVALUATE_LOG = "evaluate.csv"
"""``imssr evaluate``'s summary rows, appended."""
EVALUATE_EPISODES_LOG = "evaluate_episodes.csv"
"""``imssr evaluate``'s episode rows, appended."""
TRAINING_LOGS = (TRAIN_LOG, EVAL_LOG, EVAL_EPISODES_LOG)
"""The CSV logs a training writes."""
CSV_LOGS = TRAINING_LOGS + (EVALUATE_LOG, EVALUATE_EPISODES_LOG)
"""Every CSV log of a run: training's, then ``imssr evaluate``'s."""
TB_DIR = "tb"
"""TensorBoard's event files."""
VIDEOS_DIR = "videos"
"""Evaluation videos (training's and ``imssr evaluate --video``'s)."""
ANALYSIS_DIR = "analysis"
"""``imssr analyze``'s default output folder."""
MONTAGE_FILE = "montage.png"
"""``imssr evaluate --montage``: one frame per scene."""
LEARNING_CURVE_FILE = "learning_curve.png"
"""The learning curve that ``imssr train`` and ``imssr plot`` draw."""
EPISODE_GIF = "episode.gif"
"""``imssr demo``: one episode of the trained policy."""
WANDB_RUN_FILE = "wandb_run.json"
"""``{"id": ...}``: the W&B run that ``--resume`` continues."""
STATUS_FILE = "status.json"
"""How the last training of the run ended (:meth:`RunDir.write_status`)."""
DONE_FILE = "done.json"
"""Written by ``imssr sweep`` once a training exited 0 having reached its budget; holds the
budget in agent steps (``steps``) and frames (``frames``)."""
SWEEP_LOG = "sweep.log"
"""``imssr sweep``: the output of every attempt of the run, appended, one header line each."""
FRAMES_FILE = "replay-frames.mmap"
"""``train.replay_device=disk``: the replay frames of the training running here, memory-mapped
(:class:`~imssr.replay.buffer.DiskFrameReplayBuffer`); scratch, removed when the training ends."""
CHECKPOINT_DIR = "checkpoints"
"""Checkpoints and the replay buffer."""
LATEST_CHECKPOINT = "latest.pt"
"""The checkpoint a resume continues from."""
NUMBERED_CHECKPOINT = "step-{step:09d}.pt"
"""A retained checkpoint of agent step ``step``."""
REPLAY_FILE = "replay-{step:09d}.npz"
"""The index of the replay buffer saved with the checkpoint of agent step ``step`` (its frame
files beside it, :func:`imssr.replay.buffer.replay_files`)."""
CHECKPOINT_GLOB, REPLAY_GLOB = "step-*.pt", "replay-*"
EARLY_PARTS = TRAINING_LOGS + (VIDEOS_DIR,)
"""The parts of a run (:meth:`RunDir.run_parts`) that a training writes before its first
checkpoint, which :meth:`RunDir.discard_unresumable` may clear (with ``tb/``)."""

# What RunDir.status() answers.
NEW, RUNNING, INTERRUPTED, FINISHED, FAILED, DIVERGED = "new", "running", "interrupted", "finished", "failed", "diverged"
ENDINGS = (INTERRUPTED, FINISHED, FAILED, DIVERGED)
"""The states a training records in ``status.json`` when it ends."""

SEED_LEVEL, BETA0_LEVEL = "seed_", "beta0_"
"""The prefixes of a run path's last levels (:func:`run_path`)."""
SEED_DIR = SEED_LEVEL + "{seed}"
"""A seed's run directory inside the folder of ``imssr train --seeds``."""


def run_path(root: str, task: str, algo: str, seed: int, beta0_label: Optional[str] = None) -> str:
    """Where a run lives under ``root``: ``ROOT/<task>/<algo>/seed_<n>``, or
    ``ROOT/<task>/<algo>/beta0_<label>/seed_<n>`` for a point of a beta_0 sweep. ``imssr train``
    and ``imssr.train`` default to ``root="runs"``; a sweep's runs are these paths under its root.
    :func:`parse_run_path` reads one back."""
    beta = [] if beta0_label is None else [f"{BETA0_LEVEL}{beta0_label}"]
    return os.path.join(root, task, algo, *beta, f"{SEED_LEVEL}{seed}")


class RunPath(NamedTuple):
    """A run path's parts (:func:`parse_run_path`)."""

    root: str
    task: str
    algo: str
    seed: int
    beta0_label: Optional[str]
    """The ``beta0_<label>`` level's label; None when the path has none."""


def parse_run_path(path: str) -> Optional[RunPath]:
    """The inverse of :func:`run_path`: the parts of ``.../<task>/<algo>[/beta0_<label>]/seed_<n>``
    read from the path's end (None when it does not end so)."""
    head, seed = os.path.split(os.path.normpath(os.fspath(path)))
    if not seed.startswith(SEED_LEVEL) or not seed[len(SEED_LEVEL):].isdigit():
        return None
    head, level = os.path.split(head)
    beta = None
    if level.startswith(BETA0_LEVEL):
        beta = level[len(BETA0_LEVEL):]
        head, level = os.path.split(head)
    root, task = os.path.split(head)
    if not level or not task:
        return None
    return RunPath(root, task, level, int(seed[len(SEED_LEVEL):]), beta)


class CheckpointFile(NamedTuple):
    """A checkpoint file as found and loaded (:meth:`RunDir.checkpoint`)."""

    checkpoint: "Checkpoint"
    """What it holds: the config, the agent, the loop's state and every generator."""
    path: str
    """The file it was loaded from."""
    note: Optional[str]
    """Why it is not ``latest.pt`` when it fell back to another (None otherwise)."""


class RunDir:
    """The run directory ``path``: where its files are, its checkpoints, its config and its status."""

    def __init__(self, path: str):
        self.path = str(path)
        self._kept_replay: Optional[str] = None
        """The replay file ``latest.pt`` names, as far as this object has read or written it."""
        self._staged: Optional[tuple[int, Optional[str], bool, set[str]]] = None
        """A batch's checkpoint staged here (:meth:`stage_checkpoint`) and not yet pruned: its agent
        step, its replay file, whether its numbered copy existed before, the replay files there
        before it."""

    def __repr__(self) -> str:
        return f"RunDir({self.path!r})"

    def __fspath__(self) -> str:
        return self.path

    def file(self, name: str) -> str:
        """``RUN/name``."""
        return os.path.join(self.path, name)

    # -- layout --------------------------------------------------------------------------
    @property
    def config_path(self) -> str:
        return self.file(CONFIG_FILE)

    @property
    def train_log(self) -> str:
        return self.file(TRAIN_LOG)

    @property
    def eval_log(self) -> str:
        return self.file(EVAL_LOG)

    @property
    def eval_episodes_log(self) -> str:
        return self.file(EVAL_EPISODES_LOG)

    @property
    def evaluate_log(self) -> str:
        return self.file(EVALUATE_LOG)

    @property
    def evaluate_episodes_log(self) -> str:
        return self.file(EVALUATE_EPISODES_LOG)

    @property
    def training_logs(self) -> tuple[str, ...]:
        """The CSV logs a training writes (:data:`TRAINING_LOGS`)."""
        return tuple(self.file(name) for name in TRAINING_LOGS)

    def log(self, name: str) -> str:
        """The CSV log ``RUN/<name>.csv`` (``train``, ``eval``, ``evaluate``, ...)."""
        return self.file(f"{name}.csv")

    @property
    def tb_dir(self) -> str:
        return self.file(TB_DIR)

    @property
    def videos_dir(self) -> str:
        return self.file(VIDEOS_DIR)

    def video_path(self, name: str) -> str:
        """``RUN/videos/name``."""
        return os.path.join(self.videos_dir, name)

    @property
    def analysis_dir(self) -> str:
        return self.file(ANALYSIS_DIR)

    @property
    def montage_path(self) -> str:
        return self.file(MONTAGE_FILE)

    @property
    def learning_curve_path(self) -> str:
        return self.file(LEARNING_CURVE_FILE)

    @property
    def episode_gif_path(self) -> str:
        return self.file(EPISODE_GIF)

    @property
    def wandb_run_path(self) -> str:
        return self.file(WANDB_RUN_FILE)

    @property
    def status_path(self) -> str:
        return self.file(STATUS_FILE)

    @property
    def done_path(self) -> str:
        return self.file(DONE_FILE)

    @property
    def sweep_log(self) -> str:
        return self.file(SWEEP_LOG)

    @property
    def frames_file(self) -> str:
        """``RUN/replay-frames.mmap`` (:data:`FRAMES_FILE`)."""
        return self.file(FRAMES_FILE)

    @property
    def lock_path(self) -> str:
        return self.file(LOCK_FILE)

    @property
    def checkpoint_dir(self) -> str:
        return self.file(CHECKPOINT_DIR)

    @property
    def latest(self) -> str:
        """``checkpoints/latest.pt``."""
        return os.path.join(self.checkpoint_dir, LATEST_CHECKPOINT)

    def numbered(self, step: int) -> str:
        """``checkpoints/step-<step>.pt``."""
        return os.path.join(self.checkpoint_dir, NUMBERED_CHECKPOINT.format(step=step))

    @staticmethod
    def replay_name(step: int) -> str:
        """The name of the replay file saved with the checkpoint of agent step ``step``."""
        return REPLAY_FILE.format(step=step)

    def replay_path(self, name: str) -> str:
        """``checkpoints/<name>``: a replay file a checkpoint names."""
        return os.path.join(self.checkpoint_dir, name)

    def replay_files(self, name: str) -> list[str]:
        """The files of the replay buffer ``name``: its ``.npz`` index and the frame files it names;
        :class:`~imssr.replay.buffer.ReplayFileError` when the index cannot be read and verified."""
        from imssr.replay import buffer as replay_buffer  # torch: loaded when a run's replay is read

        return replay_buffer.replay_files(self.replay_path(name))

    def _all_replay_files(self) -> set[str]:
        return set(glob.glob(os.path.join(self.checkpoint_dir, REPLAY_GLOB)))

    def remove_unnamed_replay_files(self, name: Optional[str]) -> None:
        """Remove the replay files that the replay buffer ``name`` (None: none) does not use.  When
        the index ``name`` cannot be read and verified, what is live is unknown: nothing is removed,
        and a one-line warning says so (the next save cleans up)."""
        from imssr.replay.buffer import ReplayFileError  # torch: loaded when a run's replay is read

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
        from imssr.replay.buffer import ReplayFileError  # torch: loaded when a run's replay is read

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
        from imssr.replay.buffer import ReplayFileError  # torch: loaded when a run's replay is read

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

    # -- life ----------------------------------------------------------------------------
    @property
    def exists(self) -> bool:
        return os.path.isdir(self.path)

    def require(self) -> "RunDir":
        """Self, or a one-line error when the directory does not exist."""
        if not self.exists:
            raise ImssrError(f"run directory not found: {self.path}")
        return self

    def open(self) -> DirectoryLock:
        """Take the run for writing: its exclusive lock (created if missing; a second writer fails
        at once with "RUN is in use by PID n").  Release the returned lock when done."""
        return DirectoryLock(self.path).acquire()

    def in_use(self) -> bool:
        """Whether a process holds the run's lock now (a training runs in it)."""
        return held_by(self.path) is not None

    # -- config --------------------------------------------------------------------------
    def has_config(self) -> bool:
        return os.path.exists(self.config_path)

    def write_config(self, cfg: RunConfig) -> str:
        """Write the resolved config atomically (creating the directory)."""
        os.makedirs(self.path, exist_ok=True)
        atomic_write_text(self.config_path, cfg.to_json() + "\n")
        return self.config_path

    def read_config(self) -> RunConfig:
        """The run's config (a one-line error when it is missing or invalid)."""
        return load_config(self.config_path)

    # -- provenance ----------------------------------------------------------------------
    @property
    def provenance_path(self) -> str:
        return os.path.join(self.path, PROVENANCE_FILE)

    def record_provenance(self, record: dict) -> str:
        """Append ``record`` (:func:`imssr.provenance.record`) to the run's provenance, atomically.
        A file that cannot be read is kept beside as ``provenance.json.damaged`` and a new list
        begun; a symbolic link in its place is refused (:meth:`refuse_linked_provenance`)."""
        self.refuse_linked_provenance()
        records = self.read_provenance()
        if records is None:
            os.replace(self.provenance_path, self.provenance_path + ".damaged")
            records = []
        os.makedirs(self.path, exist_ok=True)
        atomic_write_text(self.provenance_path, dumps({"records": records + [record]}, indent=2) + "\n")
        return self.provenance_path

    def refuse_linked_provenance(self) -> None:
        """A one-line error when ``provenance.json`` is a symbolic link: the records are read back
        and rewritten whole at every start, so through a link they would take in a file from
        outside the run (or set that file aside as damaged), as a log written through one would
        (:func:`~imssr.files.open_own`)."""
        if os.path.islink(self.provenance_path):
            raise ImssrError(f"{self.provenance_path} is a symbolic link; {OWN_FILE_RULE}")

    def read_provenance(self) -> Optional[list[dict]]:
        """The provenance records, oldest first: [] when there is no file (a run of imssr before
        them), None when the file cannot be read."""
        if not os.path.exists(self.provenance_path):
            return []
        data = _read_json(self.provenance_path)
        records = data.get("records") if isinstance(data, dict) else None
        if not isinstance(records, list) or not all(isinstance(r, dict) for r in records):
            return None
        return records

    # -- what the directory holds ------------------------------------------------------------
    def run_parts(self) -> list[str]:
        """The parts of a run the directory holds, as names relative to it: any checkpoint or
        replay file, a log with a row, and what training, evaluation and analysis wrote beside
        them.  A directory with any of them is a run, which a fresh training must not replace.

        Not parts: ``config.json`` alone (a run described but not started, as a sweep writes it
        before the first attempt), the lock, ``status.json``, ``sweep.log``, the temporary files
        of a killed write, and logs with no row (a training that stopped before its first
        episode or evaluation ended)."""
        parts = []
        if os.path.isdir(self.checkpoint_dir):
            for pattern in (LATEST_CHECKPOINT, CHECKPOINT_GLOB, REPLAY_GLOB):
                parts += sorted(os.path.join(CHECKPOINT_DIR, os.path.basename(p))
                                for p in glob.glob(os.path.join(self.checkpoint_dir, pattern)))
        for name in CSV_LOGS:
            if _has_rows(self.file(name)):
                parts.append(name)
        for name in (VIDEOS_DIR, ANALYSIS_DIR, MONTAGE_FILE, LEARNING_CURVE_FILE, EPISODE_GIF, DONE_FILE):
            path = self.file(name)
            if os.path.isfile(path) or (os.path.isdir(path) and os.listdir(path)):
                parts.append(name)
        return parts

    def refuse_fresh_start(self) -> None:
        """A one-line error when the directory holds any part of a run (:meth:`run_parts`): a
        fresh training there would mix with it or replace it.  The error names ``--resume`` when
        there is a checkpoint to continue from, and what is there when there is none."""
        parts = self.run_parts()
        if not parts:
            return
        shown = ", ".join(parts[:3]) + (", ..." if len(parts) > 3 else "")
        if self.has_checkpoint():
            raise ImssrError(f"{self.path} already holds a run ({shown}); pass --resume to continue it "
                             "or choose another --out")
        raise ImssrError(f"{self.path} already holds part of a run ({shown}) but no checkpoint to resume "
                         "from; choose another --out, or remove those files to start again there")

    def discard_unresumable(self) -> list[str]:
        """Clear what a training that failed before its first checkpoint left (its CSV logs,
        ``videos/``, ``tb/``, the replay files of a save killed before its checkpoint), so that the run can start again from agent step 0, as a sweep's
        fresh attempt does; returns the names removed (those of :meth:`run_parts`).  A run with a
        checkpoint is left as it is: it resumes.  The removal holds the run's lock (a one-line
        error while a process holds it).

        Nothing that only a checkpoint can make is removed: a finished run (``done.json``, or
        ``status.json`` "finished") whose checkpoints are gone, and a directory with
        ``evaluate.csv``, ``analysis/`` and the like, are a one-line error and stay as they are."""
        if self.has_checkpoint() or not (self.run_parts() or os.path.isdir(self.tb_dir)):
            return []  # nothing to clear, no lock to take (a full disk then fails at the attempt's log)
        with DirectoryLock(self.path):
            if self.has_checkpoint():
                return []
            record = self.read_status()
            if self.read_done() is not None or (record is not None and record["state"] == FINISHED):
                raise ImssrError(f"{self.path} holds a finished run without a checkpoint; move it away to "
                                 "train it again")
            parts = self.run_parts()
            # Without a checkpoint, replay files are what a first save killed before its checkpoint
            # file wrote (a run's, or a batch's run that had not staged its checkpoint yet).
            replay = os.path.join(CHECKPOINT_DIR, REPLAY_GLOB[:-1])
            results = [name for name in parts if name not in EARLY_PARTS and not name.startswith(replay)]
            if results:
                shown = ", ".join(results[:3]) + (", ..." if len(results) > 3 else "")
                raise ImssrError(f"{self.path} holds results of a run without a checkpoint ({shown}); move it "
                                 "away to train it again")
            self._remove(parts)
            return parts

    def _remove(self, parts: list[str]) -> None:
        """Remove ``parts`` (names of :meth:`run_parts`) and ``tb/``; the caller holds the lock."""
        for name in parts + [TB_DIR]:
            path = self.file(name)
            if os.path.isdir(path):
                shutil.rmtree(path)
            elif os.path.exists(path):
                os.unlink(path)

    def _first_set_leftovers(self) -> Optional[list[str]]:
        """The parts (:meth:`run_parts`) here when they may be what a batch stopped before its
        first checkpoint was complete left (:func:`first_set_leftovers`): no ``latest.pt`` (a batch
        promotes its first only once every run staged one), no finished run, nothing but the logs,
        videos and staged checkpoint files; else None."""
        if self.has_latest() or self.read_done() is not None:
            return None
        record = self.read_status()
        if record is not None and record["state"] == FINISHED:
            return None
        parts = self.run_parts()
        staged = os.path.join(CHECKPOINT_DIR, "")
        if any(name not in EARLY_PARTS and not name.startswith(staged) for name in parts):
            return None
        return parts

    def clear_first_set_leftovers(self, parts: list[str]) -> None:
        """Remove ``parts`` (:func:`first_set_leftovers`) and ``tb/``, so that a batch starts
        afresh here; the caller holds the lock."""
        self._remove(parts)

    # -- checkpoints ---------------------------------------------------------------------
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
        steps = [_numbered_step(path) for path in self.numbered_checkpoints()]
        return [step for step in steps if step is not None]

    def save_checkpoint(self, ckpt: "Checkpoint", keep: int = 1, replay=None) -> str:
        """Write ``ckpt`` as ``latest.pt`` and its numbered copy (``keep`` > 0: the ``keep``
        newest copies stay), after the replay buffer ``replay`` when ``ckpt`` names a replay file
        (only the frames that arrived since the previous save are new files); then remove the
        replay files ``latest.pt`` no longer names and the temporary files of a process killed
        mid-write.  A save that fails (a full disk) leaves the previous ``latest.pt`` as it was and
        removes the replay files it wrote, which no checkpoint names.  Returns ``latest.pt``'s path."""
        from imssr.rundir.checkpoint import copy_checkpoint, write_checkpoint

        if ckpt.replay_file and replay is None:
            raise ValueError("a checkpoint that names a replay file is saved with its replay buffer")
        before, replay_before = _identity(self.latest), self._all_replay_files()
        try:
            if ckpt.replay_file:
                replay.save(self.replay_path(ckpt.replay_file))
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
        self.remove_unnamed_replay_files(ckpt.replay_file)
        for tmp in glob.glob(os.path.join(self.checkpoint_dir, TEMP_GLOB)):
            os.unlink(tmp)
        return path

    # A batch's checkpoint (imssr train --seeds / --runs) is a set, every run's or none: each run
    # stages its checkpoint as its numbered copy, keeping what latest.pt names; once every run has
    # staged, each promotes its copy to latest.pt, then each prunes.  At any moment every run holds
    # a checkpoint of the last step every run completed (batch_checkpoints finds it).
    def stage_checkpoint(self, ckpt: "Checkpoint", replay=None) -> str:
        """The first stage of a batch's checkpoint: ``ckpt`` as ``step-<step>.pt``, after its replay
        files (as :meth:`save_checkpoint` writes them); ``latest.pt``, the older numbered copies and
        the replay files they name stay.  A stage that fails removes what it wrote (the numbered
        copy only when it was not there before).  Returns the numbered copy's path."""
        from imssr.rundir.checkpoint import write_checkpoint

        if ckpt.replay_file and replay is None:
            raise ValueError("a checkpoint that names a replay file is saved with its replay buffer")
        path = self.numbered(ckpt.step)
        self._staged = (ckpt.step, ckpt.replay_file, os.path.exists(path), self._all_replay_files())
        try:
            if ckpt.replay_file:
                replay.save(self.replay_path(ckpt.replay_file))
            write_checkpoint(path, ckpt)
        except BaseException:
            self.unstage_checkpoint()
            raise
        return path

    def unstage_checkpoint(self) -> None:
        """Undo :meth:`stage_checkpoint` (another run of the batch failed to stage): remove the
        numbered copy and the replay files it added (only those: what ``latest.pt`` names stays,
        whether or not this object has read it)."""
        if self._staged is None:
            return
        step, _, existed, replay_before = self._staged
        self._staged = None
        if not existed and os.path.exists(self.numbered(step)):
            os.unlink(self.numbered(step))
        for new in self._all_replay_files() - replay_before:
            os.unlink(new)

    def promote_checkpoint(self) -> str:
        """The second stage, once every run of the batch staged: the staged copy becomes
        ``latest.pt`` (a real copy, written atomically).  Returns ``latest.pt``'s path."""
        from imssr.rundir.checkpoint import copy_checkpoint

        if self._staged is None:
            raise ValueError("no staged checkpoint to promote")
        step, replay_file, _, _ = self._staged
        copy_checkpoint(self.numbered(step), self.latest)
        self._kept_replay = replay_file
        return self.latest

    def prune_checkpoints(self, keep: int) -> None:
        """The last stage, once every run of the batch promoted: the ``keep`` newest numbered
        copies stay (0: none), and the replay files and temporary files ``latest.pt`` does not
        need go."""
        self._staged = None
        numbered = self.numbered_checkpoints()
        for old in numbered[:-keep] if keep > 0 else numbered:
            os.unlink(old)
        self.remove_unnamed_replay_files(self._kept_replay)
        for tmp in glob.glob(os.path.join(self.checkpoint_dir, TEMP_GLOB)):
            os.unlink(tmp)

    def return_to(self, found: CheckpointFile) -> CheckpointFile:
        """Make the checkpoint ``found`` (the one :func:`batch_checkpoints` chose) this run's
        ``latest.pt`` and remove what belongs to a checkpoint of the batch that not every run
        completed: the numbered copies of later steps and the replay files ``found`` does not
        name.  Returns ``found`` as ``latest.pt``."""
        from imssr.rundir.checkpoint import copy_checkpoint

        step, replay_file = found.checkpoint.step, found.checkpoint.replay_file
        if found.path != self.latest:
            copy_checkpoint(found.path, self.latest)
        for path in self.numbered_checkpoints():
            later = _numbered_step(path)
            if later is not None and later > step:
                os.unlink(path)
        if not replay_file or all(os.path.exists(p) for p in self.replay_files(replay_file)):
            self.remove_unnamed_replay_files(replay_file)
        self._kept_replay = replay_file
        return CheckpointFile(found.checkpoint, self.latest, found.note)

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
        # torch reads checkpoints: loaded here, so that a run's layout, logs and status need none.
        from imssr.rundir.checkpoint import CheckpointDamaged, load_checkpoint

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
        from imssr.rundir.checkpoint import CheckpointDamaged, load_checkpoint

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

    # -- logs ----------------------------------------------------------------------------
    def last_evaluation(self) -> tuple[int, int]:
        """``(agent step, frame)`` of the last complete row of ``eval.csv`` ((0, 0) if none)."""
        return _last_values(self.eval_log, ("step", "frame"))

    def trained_steps(self) -> int:
        """Agent step of the last training episode logged (0 if none)."""
        return _last_values(self.train_log, ("step",))[0]

    # -- status --------------------------------------------------------------------------
    def status(self) -> str:
        """``running`` while a process holds the run's lock; else how its last training ended as
        it recorded it (``finished``, ``interrupted``, ``failed``, ``diverged``: ``status.json``);
        else ``finished`` when a sweep marked it done, ``interrupted`` when it has a checkpoint
        (a training killed outright), and ``new`` otherwise."""
        return self.outcome()[0]

    def outcome(self) -> tuple[str, str]:
        """``(state, error)``: :meth:`status`, and for a run whose last training ``failed`` or
        ``diverged`` the error line it recorded (the state itself when it recorded none); ""
        otherwise.  What ``imssr report`` and ``imssr export`` know of how a run stands."""
        if self.in_use():
            return RUNNING, ""
        record = self.read_status()
        if record is not None:
            state = record["state"]
            error = record.get("error")
            return state, ((error if isinstance(error, str) and error else state) if state in (FAILED, DIVERGED)
                           else "")
        if self.read_done() is not None:
            return FINISHED, ""
        return (INTERRUPTED if self.has_checkpoint() else NEW), ""

    def read_status(self) -> Optional[dict]:
        """The record of how the last training ended (None: none, or unreadable)."""
        record = _read_json(self.status_path)
        return record if record is not None and record.get("state") in ENDINGS else None

    def write_status(self, state: str, step: Optional[int] = None, error: str = "") -> str:
        """Record, atomically, how a training of the run ended: ``state`` is one of
        :data:`ENDINGS`, ``step`` the agent step it reached, ``error`` its last line."""
        if state not in ENDINGS:
            raise ValueError(f"not an ending: {state!r}")
        record = {"state": state, "step": step, "error": error, "time": time.strftime("%Y-%m-%dT%H:%M:%S")}
        atomic_write_text(self.status_path, dumps(record, indent=2) + "\n")
        return self.status_path

    @contextlib.contextmanager
    def recording(self, step: Callable[[], int], interrupted: tuple[type, ...] = ()) -> Iterator[None]:
        """Record how the training run inside the block ends (:meth:`write_status`): ``finished``,
        ``interrupted`` (``interrupted`` exceptions and KeyboardInterrupt), ``diverged``
        (:class:`~imssr.errors.DivergedError`) or ``failed``, at agent step ``step()``.  Use it
        while the run is locked.  The record of how an earlier training ended is dropped as the
        block starts, since this one now runs; a start that fails before (a full disk, a config
        that does not match the checkpoint) keeps it, as the run is still what it recorded.  A
        record that cannot be written (a full disk) is left out: the error that stopped the
        training is the one to show, and the status then follows from the run's files."""
        if os.path.exists(self.status_path):
            os.unlink(self.status_path)
        try:
            yield
        except BaseException as exc:
            state = (INTERRUPTED if isinstance(exc, (KeyboardInterrupt, *interrupted)) else
                     DIVERGED if isinstance(exc, DivergedError) else FAILED)
            self._record(state, step(), str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
            raise
        self._record(FINISHED, step())

    def _record(self, state: str, step: int, error: str = "") -> None:
        try:
            self.write_status(state, step, error)
        except (ImssrError, OSError):
            pass

    def read_done(self) -> Optional[dict]:
        """The run's done marker, or None (absent, unreadable or without a budget: not done)."""
        done = _read_json(self.done_path)
        steps = None if done is None else done.get("steps")
        return done if isinstance(steps, int) and not isinstance(steps, bool) else None

    def done_steps(self) -> Optional[int]:
        """The budget in agent steps that the done marker records; None when not done."""
        done = self.read_done()
        return None if done is None else done["steps"]

    def is_done(self, steps: int) -> bool:
        """Finished with a budget of at least ``steps`` agent steps (a larger budget resumes it)."""
        budget = self.done_steps()
        return budget is not None and budget >= steps

    def write_done(self, steps: int, final_step: int, attempt: int, resumed: bool, seconds: float = 0.0) -> str:
        """Mark the run finished with a budget of ``steps`` agent steps; ``seconds`` is the last
        attempt's wall-clock time.  Frames are recorded beside the steps for people reading it."""
        try:
            repeat: Optional[int] = self.read_config().env.action_repeat
        except (ImssrError, OSError, TypeError, ValueError):
            repeat = None
        done = {"steps": steps, "frames": None if repeat is None else steps * repeat,
                "final_step": final_step, "final_frame": self.last_evaluation()[1],
                "evaluations": len(read_csv(self.eval_log)), "attempt": attempt, "resumed": resumed,
                "seconds": seconds, "finished": time.strftime("%Y-%m-%dT%H:%M:%S")}
        atomic_write_text(self.done_path, dumps(done, indent=2) + "\n")
        return self.done_path


def _identity(path: str) -> Optional[tuple]:
    """Which file ``path`` is now (None if none): tells whether a save replaced it."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


def as_run_dir(run: Union[RunDir, str, "os.PathLike[str]"]) -> RunDir:
    """``run`` as a :class:`RunDir`: what the public entry points (``imssr.train``, ``Trainer``,
    ``imssr.load_run``, ``evaluate_run``, ``analyze_run``, ``plot_learning_curve``) accept as a
    run is a path or a RunDir; everything below them is handed the RunDir."""
    return run if isinstance(run, RunDir) else RunDir(os.fspath(run))


def _numbered_step(path: str) -> Optional[int]:
    """The agent step in the name of a numbered checkpoint ``step-<step>.pt`` (None: not digits)."""
    digits = os.path.basename(path)[len("step-"):-len(".pt")]
    return int(digits) if digits.isdigit() else None


def batch_checkpoints(runs: Sequence[RunDir], budget: int) -> list[CheckpointFile]:
    """The checkpoints a batch of runs (``imssr train --seeds/--runs --resume``) continues from,
    one per run, all of one agent step: the newest step at which every run holds a checkpoint that
    verifies, ``latest.pt`` or a numbered copy (:meth:`RunDir.stage_checkpoint` keeps one of the
    last step every run completed).  A run's ``note`` says when it is not ``latest.pt``.

    One-line errors: no run has a checkpoint ("nothing to resume"; a batch that began: start
    afresh); some have none (the batch stopped during its first checkpoint: start afresh); the
    runs share no step (trained apart: the line says which to bring where alone first, then to
    resume together with ``--steps`` the budget, or the furthest run's step when that is past
    it); a run none of whose checkpoints verifies (:meth:`RunDir.checkpoint`'s error)."""
    from imssr.rundir.checkpoint import CheckpointDamaged, load_checkpoint

    without = [run for run in runs if not run.has_checkpoint()]
    if len(without) == len(runs):
        if len(runs) == 1:
            raise ImssrError(f"nothing to resume: {runs[0].latest} does not exist")
        # What a batch writes before its first checkpoint is whole (logs, a staged checkpoint or
        # its temporary file) is cleared by a fresh start of the batch.
        began = first_set_leftovers(runs) is not None or any(
            glob.glob(os.path.join(run.checkpoint_dir, TEMP_GLOB)) for run in runs)
        raise ImssrError("nothing to resume: no run of the batch holds a checkpoint"
                         + (" (the batch stopped before its first checkpoint was complete)" if began else "")
                         + "; start every run afresh: the same command without --resume")
    if without:
        raise ImssrError(f"nothing to resume as one batch: {_some(r.path for r in without)} "
                         f"{'holds' if len(without) == 1 else 'hold'} no checkpoint (the batch stopped during its "
                         "first one); start every run afresh: the same command without --resume")
    loaded: dict[str, "Checkpoint"] = {}
    damaged: dict[str, str] = {}
    offers: list[dict[int, str]] = []  # per run: agent step -> the file that holds it
    for run in runs:
        offer = {step: run.numbered(step) for step in run.checkpoint_steps()}
        if run.has_latest():
            try:
                ckpt = loaded[run.latest] = load_checkpoint(run.latest)
                offer[ckpt.step] = run.latest
            except CheckpointDamaged as exc:
                damaged[run.latest] = exc.reason
        offers.append(offer)
    while True:
        for run, offer in zip(runs, offers):
            if not offer:
                run.checkpoint()  # raises: none of its checkpoints verifies, in its own words
        common = set.intersection(*(set(offer) for offer in offers))
        if not common:
            newest = [max(offer) for offer in offers]
            furthest = max(newest)
            behind = [run.path for run, step in zip(runs, newest) if step < furthest]
            ahead = [run.path for run, step in zip(runs, newest) if step == furthest]
            held = "; ".join(f"{run.path}: {', '.join(map(str, sorted(offer)))}" for run, offer in
                             list(zip(runs, offers))[:3]) + ("; ..." if len(runs) > 3 else "")
            # A budget below the furthest run's step would refuse that run: the batch resumes
            # with a budget it can reach.
            past = "" if budget >= furthest else \
                f" ({_some(ahead)} {'is' if len(ahead) == 1 else 'are'} already past --steps {budget})"
            raise ImssrError(f"the runs hold no checkpoint of one agent step in common (agent steps {held}): "
                             f"bring {_some(behind)} to step {furthest} alone first (imssr train --out RUN_DIR "
                             f"--resume --steps {furthest}), then resume them together with "
                             f"--steps {max(budget, furthest)}{past}")
        step = max(common)
        found = []
        for run, offer in zip(runs, offers):
            path = offer[step]
            if path not in loaded:
                try:
                    loaded[path] = load_checkpoint(path)
                    if loaded[path].step != step:
                        raise CheckpointDamaged(f"{path} holds agent step {loaded[path].step}", path,
                                                "another agent step than its name")
                except CheckpointDamaged as exc:
                    damaged[path] = exc.reason
                    del offer[step]  # the next common step, if any
                    break
            found.append(CheckpointFile(loaded[path], path, _batch_note(run, path, step, loaded, damaged)))
        else:
            return found


def first_set_leftovers(runs: Sequence[RunDir]) -> Optional[list[list[str]]]:
    """What a batch stopped before its first checkpoint was complete left in its runs, per run
    (names of :meth:`RunDir.run_parts`: logs, videos, the checkpoints some runs staged), for a
    fresh start of the batch to clear; None when there is nothing to clear or the runs hold
    anything else: a ``latest.pt`` or results of a run, a finished run, or a numbered checkpoint
    every run holds (a whole checkpoint of the batch, which ``--resume`` continues)."""
    parts = [run._first_set_leftovers() for run in runs]
    if any(p is None for p in parts) or not any(parts):
        return None
    if set.intersection(*(set(run.checkpoint_steps()) for run in runs)):
        return None
    return parts  # type: ignore[return-value]


def _batch_note(run: RunDir, path: str, step: int, loaded: dict, damaged: dict) -> Optional[str]:
    """Why ``run`` resumes from ``path`` and not ``latest.pt`` (None when it is latest.pt)."""
    if path == run.latest:
        return None
    there = f"{run.path}: resuming from {os.path.basename(path)} at agent step {step}"
    if run.latest in damaged:
        return f"{run.latest} is damaged ({damaged[run.latest]}); {there}"
    if run.latest not in loaded:
        return f"{run.latest} is missing; {there}"
    latest = loaded[run.latest].step
    why = (f"its latest.pt, of agent step {latest}, is of a checkpoint the other runs lack" if latest > step
           else f"its latest.pt is of agent step {latest}")
    return f"{there}, the last checkpoint every run of the batch completed ({why})"


def _some(names: Iterable[str], shown: int = 3) -> str:
    """The first ``shown`` of ``names`` joined by commas, "..." after them when there are more."""
    names = list(names)
    return ", ".join(names[:shown]) + (", ..." if len(names) > shown else "")


def _read_json(path: str) -> Optional[dict]:
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError, RecursionError):  # ValueError: bad JSON or not UTF-8
        return None
    return data if isinstance(data, dict) else None


def _has_rows(path: str) -> bool:
    """Whether the CSV file ``path`` holds a row below its header."""
    try:
        with open(path, "rb") as fh:
            fh.readline()
            return bool(fh.readline().strip())
    except OSError:
        return False


def _last_values(path: str, columns: tuple[str, ...]) -> tuple[int, ...]:
    """``columns`` of the last complete (newline-terminated) row of a CSV log (0 each if none);
    reads only the file's header and tail."""
    zero = tuple(0 for _ in columns)
    try:
        with open(path, "rb") as fh:
            header = fh.readline().decode(errors="replace").strip().split(",")
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - 4096))
            text = fh.read().decode(errors="replace")
    except OSError:
        return zero
    if any(c not in header for c in columns):
        return zero
    indices = [header.index(c) for c in columns]
    lines = text.split("\n")
    if size > 4096:
        lines = lines[1:]  # the tail's first line starts mid-row
    # The last element is "" after a complete row; anything else is a row cut short by a
    # killed writer, whose counters may be truncated (3 of 3000): ignore it.  The header itself
    # (when the file holds no row) has no digits in those columns.
    for line in reversed(lines[:-1]):
        cells = line.split(",")
        if len(cells) > max(indices) and all(cells[i].isdigit() for i in indices):
            return tuple(int(cells[i]) for i in indices)
    return zero
