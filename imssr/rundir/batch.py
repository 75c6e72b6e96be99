"""The checkpoints of a batch of runs (``imssr train --seeds`` / ``--runs``): a set, every run's
or none.

Each run stages its checkpoint as its numbered copy, keeping what ``latest.pt`` names; once every
run has staged, each promotes its copy to ``latest.pt``, then each prunes.  At any moment every
run holds a checkpoint of the last step every run completed, which :func:`batch_checkpoints`
finds; :func:`first_set_leftovers` finds what a batch stopped before its first whole set left.
"""
from __future__ import annotations

import glob
import os
from typing import TYPE_CHECKING, Optional, Sequence

import imssr.rundir.checkpoint as checkpoint_file
from imssr.errors import ImssrError
from imssr.files import TEMP_GLOB
from imssr.rundir.checkpoint import Checkpoint, CheckpointDamaged, CheckpointFile, load_checkpoint
from imssr.rundir.layout import CHECKPOINT_DIR, EARLY_PARTS, RunLayout, some

if TYPE_CHECKING:
    from imssr.rundir.directory import RunDir


class BatchCheckpoints(RunLayout):
    """One run's part in its batch's checkpoints (a part of :class:`~imssr.rundir.RunDir`, built on
    its checkpoints and what the directory holds: ``run_parts``)."""

    _staged: Optional[tuple[int, Optional[str], bool, set[str]]] = None
    """A batch's checkpoint staged here (:meth:`stage_checkpoint`) and not yet pruned: its agent
    step, its replay file, whether its numbered copy existed before, the replay files there
    before it."""
    _kept_replay: Optional[str] = None
    """The replay file ``latest.pt`` names, as this object promoted or returned to it."""

    def stage_checkpoint(self, ckpt: Checkpoint, replay=None) -> str:
        """The first stage of a batch's checkpoint: ``ckpt`` as ``step-<step>.pt``, after its replay
        files (as :meth:`save_checkpoint` writes them); ``latest.pt``, the older numbered copies and
        the replay files they name stay.  A stage that fails removes what it wrote (the numbered
        copy only when it was not there before).  Returns the numbered copy's path."""
        path = self.numbered(ckpt.step)
        self._staged = (ckpt.step, ckpt.replay_file, os.path.exists(path), self._all_replay_files())
        try:
            self.write_replay(ckpt, replay)
            checkpoint_file.write_checkpoint(path, ckpt)
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
        if self._staged is None:
            raise ValueError("no staged checkpoint to promote")
        step, replay_file, _, _ = self._staged
        checkpoint_file.copy_checkpoint(self.numbered(step), self.latest)
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
        self._remove_unneeded(self._kept_replay)

    def return_to(self, found: CheckpointFile) -> CheckpointFile:
        """Make the checkpoint ``found`` (the one :func:`batch_checkpoints` chose) this run's
        ``latest.pt`` and remove what belongs to a checkpoint of the batch that not every run
        completed: the numbered copies of later steps and the replay files ``found`` does not
        name.  Returns ``found`` as ``latest.pt``."""
        step, replay_file = found.checkpoint.step, found.checkpoint.replay_file
        if found.path != self.latest:
            checkpoint_file.copy_checkpoint(found.path, self.latest)
        for path in self.numbered_checkpoints():
            later = os.path.basename(path)[len("step-"):-len(".pt")]
            if later.isdigit() and int(later) > step:
                os.unlink(path)
        if not replay_file or all(os.path.exists(p) for p in self.replay_files(replay_file)):
            self.remove_unnamed_replay_files(replay_file)
        self._kept_replay = replay_file
        return CheckpointFile(found.checkpoint, self.latest, found.note)

    def _first_set_leftovers(self) -> Optional[list[str]]:
        """The parts (:meth:`run_parts`) here when they may be what a batch stopped before its
        first checkpoint was complete left (:func:`first_set_leftovers`): no ``latest.pt`` (a batch
        promotes its first only once every run staged one), no finished run, nothing but the logs,
        videos and staged checkpoint files; else None."""
        if self.has_latest() or self.recorded_finished():
            return None
        parts = self.run_parts()
        staged = os.path.join(CHECKPOINT_DIR, "")
        if any(name not in EARLY_PARTS and not name.startswith(staged) for name in parts):
            return None
        return parts

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
        raise ImssrError(f"nothing to resume as one batch: {some(r.path for r in without)} "
                         f"{'holds' if len(without) == 1 else 'hold'} no checkpoint (the batch stopped during its "
                         "first one); start every run afresh: the same command without --resume")
    loaded: dict[str, Checkpoint] = {}
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
            held = some((f"{run.path}: {', '.join(map(str, sorted(offer)))}" for run, offer in zip(runs, offers)),
                        sep="; ")
            # A budget below the furthest run's step would refuse that run: the batch resumes
            # with a budget it can reach.
            past = "" if budget >= furthest else \
                f" ({some(ahead)} {'is' if len(ahead) == 1 else 'are'} already past --steps {budget})"
            raise ImssrError(f"the runs hold no checkpoint of one agent step in common (agent steps {held}): "
                             f"bring {some(behind)} to step {furthest} alone first (imssr train --out RUN_DIR "
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
