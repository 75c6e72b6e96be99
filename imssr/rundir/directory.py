"""A run directory: the one place that knows its layout and its life.

:class:`RunDir` is made of one part per concern, each a class of its own module: where each file
lies (:mod:`~imssr.rundir.layout`), the records and how the run stands (:mod:`~imssr.rundir.records`),
its checkpoints (:mod:`~imssr.rundir.checkpoint`) and its part in its batch's set of checkpoints
(:mod:`~imssr.rundir.batch`); and this module's own: what the directory holds of a run, which a
fresh start must not replace or may clear, and the lock a writer takes.

Readers (``imssr evaluate``, ``analyze``, ``report``, :class:`imssr.api.Run`) take no lock:
every file they read is replaced atomically.
"""
from __future__ import annotations

import glob
import os
import shutil
from typing import Union

from imssr.errors import ImssrError
from imssr.rundir.batch import BatchCheckpoints
from imssr.rundir.checkpoint import Checkpoints
from imssr.rundir.layout import (ANALYSIS_DIR, CHECKPOINT_DIR, CHECKPOINT_GLOB, CSV_LOGS, DONE_FILE, EARLY_PARTS,
                                 EPISODE_GIF, LATEST_CHECKPOINT, LEARNING_CURVE_FILE, MONTAGE_FILE, REPLAY_GLOB,
                                 TB_DIR, VIDEOS_DIR, some)
from imssr.rundir.lock import DirectoryLock
from imssr.rundir.records import Records


class RunDir(BatchCheckpoints, Checkpoints, Records):
    """The run directory ``path``: where its files are, its checkpoints, its config and its status."""

    def open(self) -> DirectoryLock:
        """Take the run for writing: its exclusive lock (created if missing; a second writer fails
        at once with "RUN is in use by PID n").  Release the returned lock when done."""
        return DirectoryLock(self.path).acquire()

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
        parts += [name for name in CSV_LOGS if _has_rows(self.file(name))]
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
        if self.has_checkpoint():
            raise ImssrError(f"{self.path} already holds a run ({some(parts)}); pass --resume to continue it "
                             "or choose another --out")
        raise ImssrError(f"{self.path} already holds part of a run ({some(parts)}) but no checkpoint to resume "
                         "from; choose another --out, or remove those files to start again there")

    def discard_unresumable(self) -> list[str]:
        """Clear what a training that failed before its first checkpoint left (its CSV logs,
        ``videos/``, ``tb/``, the replay files of a save killed before its checkpoint), so that the
        run can start again from agent step 0, as a sweep's fresh attempt does; returns the names
        removed (those of :meth:`run_parts`).  A run with a checkpoint is left as it is: it resumes.
        The removal holds the run's lock (a one-line error while a process holds it).

        Nothing that only a checkpoint can make is removed: a finished run (``done.json``, or
        ``status.json`` "finished") whose checkpoints are gone, and a directory with
        ``evaluate.csv``, ``analysis/`` and the like, are a one-line error and stay as they are."""
        if self.has_checkpoint() or not (self.run_parts() or os.path.isdir(self.tb_dir)):
            return []  # nothing to clear, no lock to take (a full disk then fails at the attempt's log)
        with DirectoryLock(self.path):
            if self.has_checkpoint():
                return []
            if self.recorded_finished():
                raise ImssrError(f"{self.path} holds a finished run without a checkpoint; move it away to "
                                 "train it again")
            parts = self.run_parts()
            # Without a checkpoint, replay files are what a first save killed before its checkpoint
            # file wrote (a run's, or a batch's run that had not staged its checkpoint yet).
            replay = os.path.join(CHECKPOINT_DIR, REPLAY_GLOB[:-1])
            results = [name for name in parts if name not in EARLY_PARTS and not name.startswith(replay)]
            if results:
                raise ImssrError(f"{self.path} holds results of a run without a checkpoint ({some(results)}); "
                                 "move it away to train it again")
            self.remove_parts(parts)
            return parts

    def remove_parts(self, parts: list[str]) -> None:
        """Remove ``parts`` (names of :meth:`run_parts`) and ``tb/``: what a training that failed before
        its first checkpoint left (:meth:`discard_unresumable`), or a batch stopped before its first
        whole set of checkpoints (:func:`~imssr.rundir.first_set_leftovers`); the caller holds the lock."""
        for name in parts + [TB_DIR]:
            path = self.file(name)
            if os.path.isdir(path):
                shutil.rmtree(path)
            elif os.path.exists(path):
                os.unlink(path)


def as_run_dir(run: Union[RunDir, str, "os.PathLike[str]"]) -> RunDir:
    """``run`` as a :class:`RunDir`: what the public entry points (``imssr.train``, ``Trainer``,
    ``imssr.load_run``, ``evaluate_run``, ``analyze_run``, ``plot_learning_curve``) accept as a
    run is a path or a RunDir; everything below them is handed the RunDir."""
    return run if isinstance(run, RunDir) else RunDir(os.fspath(run))


def _has_rows(path: str) -> bool:
    """Whether the CSV file ``path`` holds a row below its header."""
    try:
        with open(path, "rb") as fh:
            fh.readline()
            return bool(fh.readline().strip())
    except OSError:
        return False
