"""A sweep directory: the one place that knows the sweep's own files, as
:class:`~imssr.rundir.RunDir` knows a run's.  Layout of ``ROOT/``::

    sweep.json             the expanded grid: the sweep's settings and every run (:class:`PlannedRun`)
    sweep_status.json      every run's state as the last ``imssr sweep`` over ROOT left it
                           (:class:`RunStatus`), rewritten on every change
    .imssr.lock            held while a sweep runs over ROOT (:mod:`imssr.rundir.lock`)
    .submitit/<job id>/    ``--launcher slurm``: submitit's job files and SLURM's output
    <task>/<algo>/[beta0_<value>/]seed_<n>/
                           one run each; its ``sweep.log`` holds the output of every attempt

Both JSON files are written atomically and read back verified: a damaged one is one
:class:`~imssr.errors.ImssrError` line naming it.
"""
from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Optional

from imssr.errors import ImssrError
from imssr.files import atomic_write_text
from imssr.jsonio import dumps, read_json
from imssr.rundir.lock import DirectoryLock, held_by
from imssr.sweep.grid import Run, SweepConfig, group_label

if TYPE_CHECKING:
    from imssr.config import RunConfig

PLAN_FILE = "sweep.json"
"""The expanded grid (:meth:`SweepDir.write_plan`)."""
STATUS_FILE = "sweep_status.json"
"""The state of every run (:meth:`SweepDir.write_status`)."""
SUBMITIT_DIR = ".submitit"
"""submitit's job scripts, pickled calls and SLURM's output (``%j`` per job)."""
STATES = ("queued", "running", "done", "failed", "interrupted")
"""What :attr:`RunStatus.state` can be; ``sweep_status.json`` counts the runs in each."""


@dataclass(frozen=True)
class PlannedRun:
    """A run of the sweep's grid with what its resolved config says of it: a row of ``sweep.json``."""

    run: Run
    """Which run."""
    steps: int
    """The run's budget T in agent steps."""
    frames: Optional[int] = None
    """The same budget in environment frames (None: a plan written without it)."""
    precision: str = "fp32"
    """The run's numerics, ``agent.precision_label`` (a plan written without it: the presets' fp32)."""

    @property
    def label(self) -> str:
        """The run's group in reports (:func:`~imssr.sweep.grid.group_label`)."""
        return group_label(self.run.algo, self.run.beta0, self.precision)


@dataclass
class RunStatus:
    """What the sweep knows about one run; a row of ``sweep_status.json``."""

    run: Run
    """Which run."""
    steps: int
    """The run's budget T in agent steps."""
    frames: int
    """The same budget in environment frames (``steps * action_repeat``)."""
    state: str = "queued"
    """queued, running, done, failed, or interrupted (stopped by a signal with its checkpoint: the
    next sweep over the root resumes it)."""
    action: str = "fresh"
    """What the sweep found: ``done`` (skipped), ``resume`` (a checkpoint) or ``fresh``."""
    attempts: int = 0
    """Attempts started by this invocation of the sweep."""
    errors: list[str] = field(default_factory=list)
    """Last output line of each failed attempt (``killed by signal N (NAME)`` for one a signal
    ended without a word)."""
    interruptions: int = 0
    """Attempts of this invocation stopped by a signal (resumed, not counted as failures)."""
    note: str = ""
    """Why the sweep did what it did when it is not plain (a divergence that is not retried)."""
    final_step: int = 0
    """Agent step of the run's last evaluation."""
    final_frame: int = 0
    """Environment frame of the run's last evaluation."""
    seconds: float = 0.0
    """Wall time of this invocation's attempts."""
    config: Optional["RunConfig"] = None
    """The run's resolved config, which the sweep writes to its ``config.json`` before the first
    attempt (:meth:`imssr.sweep.grid.Run.resolved_config`); not part of the row."""

    def to_dict(self, root: str) -> dict:
        """The row, with the run's directory and ``sweep.log`` relative to ``root``."""
        return {"name": self.run.name, "dir": os.path.relpath(self.run.dir, root), "algo": self.run.algo,
                "task": self.run.task, "seed": self.run.seed, "beta0": self.run.beta0, "steps": self.steps,
                "frames": self.frames, "state": self.state, "action": self.action, "attempts": self.attempts,
                "errors": self.errors, "interruptions": self.interruptions, "note": self.note,
                "final_step": self.final_step, "final_frame": self.final_frame, "seconds": round(self.seconds, 1),
                "log": os.path.relpath(self.run.run_dir.sweep_log, root)}

    @classmethod
    def from_dict(cls, row: Any, root: str, what: str = "the run") -> "RunStatus":
        """A row read back (``root``: the directory it is relative to; a missing counter reads as
        its default).  ValueError: not a row (its message names the row as ``what``)."""
        fields = _Fields(row, what)
        run = fields.run(root)
        state = fields.get("state", str)
        if state not in STATES:
            raise ValueError(f"{what} has state {state!r}, not one of {', '.join(STATES)}")
        errors = fields.get("errors", list, [])
        if not all(isinstance(e, str) for e in errors):
            raise ValueError(f"{what} has 'errors' that are not all text")
        return cls(run, fields.get("steps", int, 0), fields.get("frames", int, 0), state,
                   fields.get("action", str, "fresh"), fields.get("attempts", int, 0), errors,
                   fields.get("interruptions", int, 0), fields.get("note", str, ""), fields.get("final_step", int, 0),
                   fields.get("final_frame", int, 0), float(fields.get("seconds", (int, float), 0.0)))


class _Fields:
    """The values of a JSON object (a row of the sweep's files), each checked for its type."""

    _REQUIRED = object()

    def __init__(self, row: Any, what: str):
        if not isinstance(row, dict):
            raise ValueError(f"{what} is not an object but {type(row).__name__}")
        self.row, self.what = row, what

    def get(self, key: str, kind: type | tuple[type, ...], default: Any = _REQUIRED) -> Any:
        """``row[key]`` when it is of type ``kind`` (never a bool for a number); ``default`` when the key is absent
        or null (a non-finite number is written as null), if there is one; ValueError otherwise."""
        value = self.row.get(key)
        if value is None:
            if default is self._REQUIRED:
                raise ValueError(f"{self.what} has no {key!r}")
            return default
        if not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool):
            raise ValueError(f"{self.what} has {key!r} {value!r}")
        return value

    def run(self, root: str) -> Run:
        """The run the row names, its directory relative to ``root``."""
        return Run(self.get("algo", str), self.get("task", str), self.get("seed", int),
                   self.get("beta0", (int, float), None), os.path.join(root, self.get("dir", str)))


class SweepDir:
    """The sweep directory ``root``: where its files are, and its plan and status written and
    read back (:mod:`imssr.sweep.directory`)."""

    def __init__(self, root: str):
        self.given = os.fspath(root)
        """The root as the user gave it: what messages about it name."""
        self.path = os.path.abspath(self.given)
        """The root, absolute."""
        self.plan_path = os.path.join(self.path, PLAN_FILE)
        self.status_path = os.path.join(self.path, STATUS_FILE)
        self.submitit_dir = os.path.join(self.path, SUBMITIT_DIR)

    def __repr__(self) -> str:
        return f"SweepDir({self.path!r})"

    def lock(self) -> DirectoryLock:
        """The root's lock, one sweep over it at a time (a second fails at once with "ROOT is in use
        by PID n"); taken by ``with``."""
        return DirectoryLock(self.given)

    # -- sweep.json ----------------------------------------------------------------------
    def write_plan(self, cfg: SweepConfig, planned: list[PlannedRun]) -> str:
        """Write ``sweep.json`` atomically: the sweep's settings and every planned run, its
        directory relative to the root."""
        plan = {"sweep": asdict(cfg),
                "runs": [dict(asdict(p.run), dir=os.path.relpath(p.run.dir, self.path), steps=p.steps,
                              frames=p.frames, precision=p.precision) for p in planned]}
        atomic_write_text(self.plan_path, dumps(plan, indent=2) + "\n")
        return self.plan_path

    def read_plan(self) -> list[PlannedRun]:
        """The planned runs, in the plan's order ([] when there is no plan)."""
        def planned(row: Any, what: str) -> PlannedRun:
            fields = _Fields(row, what)
            return PlannedRun(fields.run(self.path), fields.get("steps", int), fields.get("frames", int, None),
                              fields.get("precision", str, "fp32"))

        return self._rows(self.plan_path, "sweep plan", planned)

    def _rows(self, path: str, what: str, read: Callable[[Any, str], Any]) -> list:
        """``read(row, "run N")`` of each row of the file's ``runs`` ([] when there is no file); a
        one-line error naming the file as ``what`` when it is damaged."""
        if not os.path.exists(path):
            return []
        try:
            rows = _Fields(read_json(path, what), "the file").get("runs", list)
            return [read(row, f"run {i + 1}") for i, row in enumerate(rows)]
        except ValueError as exc:
            raise ImssrError(f"{what} {path} is damaged: {exc}") from None

    # -- sweep_status.json ---------------------------------------------------------------
    def write_status(self, statuses: list[RunStatus], started: float, retries: int, finished: bool = False) -> str:
        """Write ``sweep_status.json`` atomically: when the sweep started and when this was written,
        whether it finished, its retries, how many runs are in each state, and every run's row."""
        counts = {s: sum(st.state == s for st in statuses) for s in STATES}
        data = {"root": self.path, "started": _iso(started), "updated": _iso(time.time()), "finished": finished,
                "retries": retries, "counts": counts, "runs": [s.to_dict(self.path) for s in statuses]}
        atomic_write_text(self.status_path, dumps(data, indent=2) + "\n")
        return self.status_path

    def read_status(self) -> list[RunStatus]:
        """Every run's row as the last sweep wrote it ([] when there is none; without the resolved
        config).  A row ``running`` while neither a sweep holds the root's lock nor a training the
        run's is read as ``interrupted``: its sweep was killed before it could say so."""
        statuses = self._rows(self.status_path, "sweep status",
                              lambda row, what: RunStatus.from_dict(row, self.path, what))
        if any(st.state == "running" for st in statuses) and held_by(self.path) is None:
            for st in statuses:
                if st.state == "running" and not st.run.run_dir.in_use():
                    st.state = "interrupted"
                    st.note = st.note or "its sweep ended while it ran (killed): the next sweep resumes it"
        return statuses

    def failed_runs(self) -> dict[str, str]:
        """The runs the last sweep gave up on and that have not finished since: run directory
        (absolute) -> the last attempt's error line.  An unreadable file or row lists none."""
        def status(row: Any, what: str) -> Optional[RunStatus]:
            try:
                return RunStatus.from_dict(row, self.path, what)
            except ValueError:
                return None

        try:
            statuses = self._rows(self.status_path, "sweep status", status)
        except (ImssrError, OSError):
            return {}
        out = {}
        for st in statuses:
            if st is not None and st.state == "failed" and st.run.run_dir.read_done() is None:
                last = st.errors[-1] if st.errors else ""
                out[os.path.abspath(st.run.dir)] = last.removeprefix("imssr: error: ") or "no error recorded"
        return out


def _iso(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(t))
