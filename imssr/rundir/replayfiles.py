"""A run's replay files: the replay buffer saved with a checkpoint (its ``.npz`` index in
``checkpoints/`` and the frame files it names, :mod:`imssr.replay.buffer`), saved, loaded and
cleaned up.  torch is loaded only where a run's replay is read or written."""
from __future__ import annotations

import glob
import os
from typing import TYPE_CHECKING, Optional

from imssr.errors import ImssrError
from imssr.rundir.layout import REPLAY_GLOB, RunLayout

if TYPE_CHECKING:
    from imssr.rundir.checkpoint import Checkpoint
    from imssr.rundir.checkpoints import CheckpointFile


class ReplayFiles(RunLayout):
    """The replay files of the run's checkpoints (a part of :class:`~imssr.rundir.RunDir`)."""

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

    def load_replay(self, found: "CheckpointFile", replay, refill: bool = False) -> Optional[str]:
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

