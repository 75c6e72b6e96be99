"""A run's records and how it stands: its resolved config (``config.json``), its provenance
(``provenance.json``, a record per start and resume), how its last training ended
(``status.json``), whether a sweep marked it done (``done.json``), and how far its logs reach."""
from __future__ import annotations

import contextlib
import json
import os
import time
from typing import Callable, Iterator, Optional

from imssr.config import RunConfig, load_config
from imssr.errors import DivergedError, ImssrError
from imssr.files import OWN_FILE_RULE, atomic_write_text, read_csv
from imssr.jsonio import dumps
from imssr.rundir.layout import DIVERGED, ENDINGS, FAILED, FINISHED, INTERRUPTED, NEW, RUNNING, RunLayout
from imssr.rundir.lock import held_by


class Records(RunLayout):
    """The run's records, and its status that follows from them (a part of
    :class:`~imssr.rundir.RunDir`, whose checkpoints it reads: ``has_checkpoint``)."""

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

    # -- status ----------------------------------------------------------------------------
    def in_use(self) -> bool:
        """Whether a process holds the run's lock now (a training runs in it)."""
        return held_by(self.path) is not None

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

    def recorded_finished(self) -> bool:
        """Whether the run's records say a training finished it: a sweep's done marker, or
        ``status.json`` "finished" (its checkpoints may be gone since)."""
        record = self.read_status()
        return self.read_done() is not None or (record is not None and record["state"] == FINISHED)

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
        state, error = FINISHED, ""
        try:
            yield
        except BaseException as exc:
            state = (INTERRUPTED if isinstance(exc, (KeyboardInterrupt, *interrupted)) else
                     DIVERGED if isinstance(exc, DivergedError) else FAILED)
            error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise
        finally:
            with contextlib.suppress(ImssrError, OSError):
                self.write_status(state, step(), error)

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

    # -- progress, from the logs ---------------------------------------------------------
    def last_evaluation(self) -> tuple[int, int]:
        """``(agent step, frame)`` of the last complete row of ``eval.csv`` ((0, 0) if none)."""
        return _last_values(self.eval_log, ("step", "frame"))

    def trained_steps(self) -> int:
        """Agent step of the last training episode logged (0 if none)."""
        return _last_values(self.train_log, ("step",))[0]


def _read_json(path: str) -> Optional[dict]:
    """The JSON object in ``path``; None when it is missing, unreadable or not an object."""
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError, RecursionError):  # ValueError: bad JSON or not UTF-8
        return None
    return data if isinstance(data, dict) else None


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
