"""Where a run's files lie: their names, the run paths of a root, and :class:`RunLayout`, the paths
of one run directory.

Layout of ``RUN/`` (every name below is a constant of this module)::

    config.json             the run's resolved config (what ``imssr train --config`` runs), read by every command
    provenance.json         which code and machine made it: a record per start and resume
    train.csv               one row per training episode
    eval.csv                one row per evaluation and scene during training
    eval_episodes.csv       one row per evaluation episode during training
    evaluate.csv            ``imssr evaluate``: one row per scene, appended
    evaluate_episodes.csv   ``imssr evaluate``: one row per episode, appended
    learning_curve.png      ``imssr plot`` / the end of ``imssr train``
    tb/                     TensorBoard events
    videos/                 evaluation videos (training's and ``imssr evaluate --video``'s)
    montage.png             ``imssr evaluate --montage``: one frame per scene
    episode.gif             ``imssr demo``: the trained policy
    analysis/               ``imssr analyze``
    wandb_run.json          the W&B run id a resume continues
    replay-frames.mmap      ``train.replay_device=disk``: the replay frames while a training runs
    status.json             how the last training of the run ended (see :meth:`RunDir.status`)
    done.json               ``imssr sweep``: the run reached its budget
    sweep.log               ``imssr sweep``: the output of every attempt, a header line each
    .imssr.lock             held while a process writes the run (:mod:`imssr.rundir.lock`)
    checkpoints/
        latest.pt                      the checkpoint a resume continues from
        step-<step>.pt                 the ``train.keep_checkpoints`` newest, real copies
        replay-<step>.npz              the index of the replay buffer ``latest.pt`` names
        replay-frames-<a>-<b>.npy      its frames a to b-1 (:mod:`imssr.replay.buffer`)
"""
from __future__ import annotations

import os
from typing import Iterable, NamedTuple, Optional

from imssr.errors import ImssrError
from imssr.rundir.lock import LOCK_FILE

CONFIG_FILE = "config.json"
PROVENANCE_FILE = "provenance.json"
TRAIN_LOG = "train.csv"
EVAL_LOG = "eval.csv"
EVAL_EPISODES_LOG = "eval_episodes.csv"
EVALUATE_LOG = "evaluate.csv"
EVALUATE_EPISODES_LOG = "evaluate_episodes.csv"
TRAINING_LOGS = (TRAIN_LOG, EVAL_LOG, EVAL_EPISODES_LOG)
"""The CSV logs a training writes."""
CSV_LOGS = TRAINING_LOGS + (EVALUATE_LOG, EVALUATE_EPISODES_LOG)
"""Every CSV log of a run: training's, then ``imssr evaluate``'s."""
TB_DIR = "tb"
VIDEOS_DIR = "videos"
ANALYSIS_DIR = "analysis"
MONTAGE_FILE = "montage.png"
LEARNING_CURVE_FILE = "learning_curve.png"
EPISODE_GIF = "episode.gif"
WANDB_RUN_FILE = "wandb_run.json"
STATUS_FILE = "status.json"
DONE_FILE = "done.json"
"""Written by ``imssr sweep`` once a training exited 0 having reached its budget; holds the
budget in agent steps (``steps``) and frames (``frames``)."""
SWEEP_LOG = "sweep.log"
FRAMES_FILE = "replay-frames.mmap"
"""``train.replay_device=disk``: the replay frames of the training running here, memory-mapped
(:class:`~imssr.replay.buffer.DiskFrameReplayBuffer`); scratch, removed when the training ends."""
CHECKPOINT_DIR = "checkpoints"
LATEST_CHECKPOINT = "latest.pt"
NUMBERED_CHECKPOINT = "step-{step:09d}.pt"
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


def some(names: Iterable[str], shown: int = 3, sep: str = ", ") -> str:
    """The first ``shown`` of ``names`` joined by ``sep``, "..." after them when there are more."""
    names = list(names)
    return sep.join(names[:shown]) + (f"{sep}..." if len(names) > shown else "")


def _in_run(name: str) -> property:
    """The path ``RUN/name``, as a property of :class:`RunLayout`."""
    return property(lambda self: self.file(name), doc=f"``RUN/{name}``.")


class RunLayout:
    """The run directory ``path`` and where each of its files lies (:data:`CONFIG_FILE` and the
    other names of this module); nothing here reads or writes a file."""

    def __init__(self, path: str):
        self.path = str(path)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.path!r})"

    def __fspath__(self) -> str:
        return self.path

    def file(self, name: str) -> str:
        """``RUN/name``."""
        return os.path.join(self.path, name)

    def require(self):
        """Self, or a one-line error when the directory does not exist."""
        if not os.path.isdir(self.path):
            raise ImssrError(f"run directory not found: {self.path}")
        return self

    config_path = _in_run(CONFIG_FILE)
    provenance_path = _in_run(PROVENANCE_FILE)
    train_log = _in_run(TRAIN_LOG)
    eval_log = _in_run(EVAL_LOG)
    eval_episodes_log = _in_run(EVAL_EPISODES_LOG)
    evaluate_log = _in_run(EVALUATE_LOG)
    evaluate_episodes_log = _in_run(EVALUATE_EPISODES_LOG)
    tb_dir = _in_run(TB_DIR)
    videos_dir = _in_run(VIDEOS_DIR)
    analysis_dir = _in_run(ANALYSIS_DIR)
    montage_path = _in_run(MONTAGE_FILE)
    learning_curve_path = _in_run(LEARNING_CURVE_FILE)
    episode_gif_path = _in_run(EPISODE_GIF)
    wandb_run_path = _in_run(WANDB_RUN_FILE)
    status_path = _in_run(STATUS_FILE)
    done_path = _in_run(DONE_FILE)
    sweep_log = _in_run(SWEEP_LOG)
    frames_file = _in_run(FRAMES_FILE)
    lock_path = _in_run(LOCK_FILE)
    checkpoint_dir = _in_run(CHECKPOINT_DIR)
    latest = _in_run(os.path.join(CHECKPOINT_DIR, LATEST_CHECKPOINT))

    @property
    def training_logs(self) -> tuple[str, ...]:
        """The CSV logs a training writes (:data:`TRAINING_LOGS`)."""
        return tuple(self.file(name) for name in TRAINING_LOGS)

    def log(self, name: str) -> str:
        """The CSV log ``RUN/<name>.csv`` (``train``, ``eval``, ``evaluate``, ...)."""
        return self.file(f"{name}.csv")

    def video_path(self, name: str) -> str:
        """``RUN/videos/name``."""
        return os.path.join(self.videos_dir, name)

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
