"""A run's checkpoints: which there are, the save of one (``latest.pt``, its numbered copies and
the replay files it names), and which one a command continues from or loads.

Order of a save's writes, each atomic (temporary file, fsync, rename): the frames written since
the last checkpoint (one new frame file), the replay ``.npz`` (which names the frame files that
hold live frames, with their sha256), ``latest.pt`` (which names the ``.npz``), its numbered
copy, then removal of what the new ``latest.pt`` no longer names.  A kill at any moment leaves
``latest.pt`` old or new, whole, with the replay files it names; a damaged ``latest.pt`` falls
back to the newest numbered checkpoint that verifies.  torch, which reads and writes
checkpoints, is loaded only where one is.
"""
from __future__ import annotations

import glob
import os
from typing import TYPE_CHECKING, NamedTuple, Optional

from imssr.errors import ImssrError
from imssr.files import TEMP_GLOB
from imssr.rundir.layout import CHECKPOINT_GLOB, REPLAY_GLOB, RunLayout, numbered_step

if TYPE_CHECKING:
    from imssr.rundir.checkpoint import Checkpoint


class CheckpointFile(NamedTuple):
    """A checkpoint file as found and loaded (:meth:`RunDir.checkpoint`)."""

    checkpoint: "Checkpoint"
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
        steps = [numbered_step(path) for path in self.numbered_checkpoints()]
        return [step for step in steps if step is not None]

    def save_checkpoint(self, ckpt: "Checkpoint", keep: int = 1, replay=None) -> str:
        """Write ``ckpt`` as ``latest.pt`` and its numbered copy (``keep`` > 0: the ``keep``
        newest copies stay), after the replay buffer ``replay`` when ``ckpt`` names a replay file
        (only the frames that arrived since the previous save are new files); then remove the
        replay files ``latest.pt`` no longer names and the temporary files of a process killed
        mid-write.  A save that fails (a full disk) leaves the previous ``latest.pt`` as it was and
        removes the replay files it wrote, which no checkpoint names.  Returns ``latest.pt``'s path."""
        from imssr.rundir.checkpoint import copy_checkpoint, write_checkpoint

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

    # -- the replay files a checkpoint names ----------------------------------------------
    def replay_files(self, name: str) -> list[str]:
        """The files of the replay buffer ``name``: its ``.npz`` index and the frame files it names;
        :class:`~imssr.replay.buffer.ReplayFileError` when the index cannot be read and verified."""
        from imssr.replay import buffer as replay_buffer

        return replay_buffer.replay_files(self.replay_path(name))

    def write_replay(self, ckpt: "Checkpoint", replay) -> None:
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
