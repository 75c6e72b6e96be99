"""One sweep run on a worker: ``imssr train`` as a subprocess, and the run's done marker.

The training runs in its own process so that a run cannot leak memory, threads or GL
contexts into the next one, and so that killing it (Ctrl-C on the sweep, a cancelled Ray
task) leaves only its last atomic checkpoint behind, from which the next attempt resumes.
"""
from __future__ import annotations

import ctypes
import json
import os
import signal
import subprocess
import sys
import time
from typing import Optional

from imssr.config import load_config, steps_for_frames
from imssr.errors import DIVERGED_PREFIX, INTERRUPTED_EXIT, ImssrError
from imssr.jsonio import dumps
from imssr.training.checkpoint import latest_path, numbered_checkpoints
from imssr.utils import atomic_write_text, disk_full_as_error, read_csv

DONE_FILE = "done.json"
"""Written atomically in the run directory once ``imssr train`` exits 0 having reached its budget.
Holds the budget in agent steps (``steps``) and frames (``frames``); a marker written before
budgets counted agent steps holds only ``frames`` (see :func:`done_steps`)."""
LOG_FILE = "sweep.log"
"""Output of every attempt of the run, appended, one header line per attempt."""


# Exit statuses of a training stopped by a signal: its own (it checkpointed), or the signal's when a
# second signal (or one before its handlers were in place) ended it; it resumes either way.
INTERRUPTED_STATUSES = (INTERRUPTED_EXIT, -signal.SIGTERM, -signal.SIGINT, 128 + signal.SIGTERM)


def has_checkpoint(run_dir: str) -> bool:
    """Something ``imssr train --resume`` continues from: ``latest.pt`` or a retained ``step-*.pt``
    (the resume falls back to those when ``latest.pt`` is missing or damaged)."""
    return os.path.exists(latest_path(run_dir)) or bool(numbered_checkpoints(run_dir))


def read_done(run_dir: str) -> Optional[dict]:
    """The run's done marker, or None (absent or unreadable: the run is not done)."""
    try:
        with open(os.path.join(run_dir, DONE_FILE)) as fh:
            done = json.load(fh)
    except (OSError, json.JSONDecodeError):
        return None
    if not isinstance(done, dict):
        return None
    # Old markers (budgets in frames) have no "steps"; either counter makes a marker.
    return done if any(_is_int(done.get(k)) for k in ("steps", "frames")) else None


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def action_repeat_of(run_dir: str) -> Optional[int]:
    """The run's action repeat from its ``config.json`` (any config version); None if unreadable."""
    try:
        return load_config(os.path.join(run_dir, "config.json")).env.action_repeat
    except (ImssrError, OSError, TypeError, ValueError):
        return None


def done_steps(run_dir: str, done: Optional[dict] = None) -> Optional[int]:
    """The budget in agent steps that the run's done marker records; None when not done.

    A marker written before budgets counted agent steps holds frames: its run trained
    ``ceil(frames / action_repeat)`` steps, as the config migration counts them.  Without a
    readable config the run's last evaluation step stands in (the run did reach it).
    """
    done = read_done(run_dir) if done is None else done
    if done is None:
        return None
    if _is_int(done.get("steps")):
        return done["steps"]
    repeat = action_repeat_of(run_dir)
    if repeat is not None:
        return steps_for_frames(done["frames"], repeat)
    return last_step(os.path.join(run_dir, "eval.csv"))


def is_done(run_dir: str, steps: int) -> bool:
    """Finished with a budget of at least ``steps`` agent steps (a larger budget resumes the run)."""
    budget = done_steps(run_dir)
    return budget is not None and budget >= steps


def last_value(path: str, column: str) -> int:
    """``column`` of the last complete (newline-terminated) row of a CSV log (0 if none); reads
    only the file's header and tail."""
    try:
        with open(path, "rb") as fh:
            header = fh.readline().decode(errors="replace").strip().split(",")
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - 4096))
            text = fh.read().decode(errors="replace")
    except OSError:
        return 0
    if column not in header:
        return 0
    index = header.index(column)
    lines = text.split("\n")
    if size > 4096:
        lines = lines[1:]  # the tail's first line starts mid-row
    # The last element is "" after a complete row; anything else is a row cut short by a
    # killed writer, whose counter may be truncated (3 of 3000): ignore it.  The header itself
    # (when the file holds no row) has no digits in that column.
    for line in reversed(lines[:-1]):
        cells = line.split(",")
        if len(cells) > index and cells[index].isdigit():
            return int(cells[index])
    return 0


def last_step(path: str) -> int:
    """Agent step of the last complete row of a CSV log (``eval.csv``, ``train.csv``; 0 if none)."""
    return last_value(path, "step")


def last_frame(path: str) -> int:
    """Environment frame of the last complete row of a CSV log (0 if none)."""
    return last_value(path, "frame")


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    # If the Ray worker that waits on this training is killed (force-cancelled task, Ray
    # shut down), the training must not live on as an orphan holding CPUs.

    ctypes.CDLL(None).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class RunAttempt:
    """One attempt of a run: ``imssr train`` (resuming when the run has a checkpoint) started in
    a subprocess that writes to the run's ``sweep.log``; :meth:`finish` says what happened.

    Killing the attempt (:meth:`stop`, or the death of the process that started it) leaves only
    the run's last atomic checkpoint, from which the next attempt resumes.
    """

    def __init__(self, run_dir: str, train_args: list[str], steps: int, attempt: int, threads: int = 1):
        os.makedirs(run_dir, exist_ok=True)
        self.run_dir, self.steps, self.attempt = run_dir, steps, attempt
        self.resumed = has_checkpoint(run_dir)
        # A resume passes the same settings so that `imssr train` rejects a run directory whose
        # config differs from the sweep's (apart from the budget and logging settings).
        cmd = [sys.executable, "-m", "imssr", "train", *train_args, "--out", run_dir, "--no-progress"]
        if self.resumed:
            cmd.append("--resume")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # One thread pool per reserved CPU: torch's default (every core) makes parallel runs spin
        # against each other, which on a shared 2-core machine is 10x slower than one thread each.
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env[var] = str(max(1, threads))
        self.log_path = os.path.join(run_dir, LOG_FILE)
        self.start = time.time()
        self.proc: Optional[subprocess.Popen] = None
        self.error = ""
        header = (f"==> attempt {attempt} ({'resume' if self.resumed else 'fresh'}) at "
                  f"{time.strftime('%Y-%m-%d %H:%M:%S')}: {' '.join(cmd)}\n")
        try:
            log = _open_log(self.log_path, header)
        except ImssrError as exc:  # a full disk: the attempt fails in one line, nothing started
            self.error = str(exc)
            return
        with log:
            self.offset = log.tell()
            preexec = _die_with_parent if sys.platform.startswith("linux") else None
            self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                         preexec_fn=preexec, start_new_session=True)

    def poll(self) -> Optional[int]:
        """The exit status, or None while the training runs."""
        return None if self.proc is None else self.proc.poll()

    def stop(self) -> None:
        """SIGTERM the training (its process group), SIGKILL after 30 s."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()

    def finish(self) -> dict:
        """What the finished attempt did (see :func:`execute_run`); writes ``done.json`` when the
        run reached its budget."""
        if self.proc is None:
            return {"ok": False, "returncode": None, "resumed": self.resumed, "error": self.error,
                    "interrupted": False, "diverged": False, "final_step": 0, "final_frame": 0,
                    "seconds": 0.0}
        returncode = self.proc.wait()
        eval_csv = os.path.join(self.run_dir, "eval.csv")
        final_step, final_frame = last_step(eval_csv), last_frame(eval_csv)
        result = {"ok": False, "returncode": returncode, "resumed": self.resumed, "error": "",
                  "interrupted": returncode in INTERRUPTED_STATUSES, "diverged": False,
                  "final_step": final_step, "final_frame": final_frame,
                  "seconds": round(time.time() - self.start, 1)}
        if returncode != 0:
            result["error"] = _last_line(self.log_path, self.offset) or f"exit status {returncode}"
            result["diverged"] = DIVERGED_PREFIX in result["error"]
        elif final_step < self.steps:
            result["error"] = (f"exited 0 but its last evaluation is at agent step {final_step}, "
                               f"before its budget of {self.steps} steps")
        else:
            result["ok"] = True
            write_done(self.run_dir, self.steps, final_step, self.attempt, self.resumed, result["seconds"])
        return result


def execute_run(run_dir: str, train_args: list[str], steps: int, attempt: int,
                threads: int = 1) -> dict:
    """Train (or resume) one run to ``steps`` agent steps and wait for it; return what happened
    (the body of a Ray task or a SLURM job).

    Result keys: ``ok``, ``returncode``, ``resumed``, ``error`` (the attempt's last output
    line when it failed), ``interrupted`` (stopped by a signal: resume it, it did not fail),
    ``diverged`` (a resume would diverge again from the same checkpoint: do not retry),
    ``final_step`` and ``final_frame`` (of the last evaluation), ``seconds``.
    """
    attempt_ = RunAttempt(run_dir, train_args, steps, attempt, threads)
    try:
        if attempt_.proc is not None:
            attempt_.proc.wait()
    finally:
        attempt_.stop()  # interrupted while waiting (task cancelled): nothing outlives it
    return attempt_.finish()


def _open_log(path: str, header: str):
    """``path`` opened for appending, ``header`` written; a full disk is one ImssrError line."""
    with disk_full_as_error(path):
        log = open(path, "a")
        try:
            log.write(header)
            log.flush()
        except BaseException:
            log.close()
            raise
    return log


def write_done(run_dir: str, steps: int, final_step: int, attempt: int, resumed: bool,
               seconds: float = 0.0) -> None:
    """Mark the run finished with a budget of ``steps`` agent steps; ``seconds`` is the last
    attempt's wall-clock time.  Frames are recorded beside the steps for people reading it."""
    evals = read_csv(os.path.join(run_dir, "eval.csv"))
    repeat = action_repeat_of(run_dir)
    done = {"steps": steps, "frames": None if repeat is None else steps * repeat,
            "final_step": final_step, "final_frame": last_frame(os.path.join(run_dir, "eval.csv")),
            "evaluations": len(evals), "attempt": attempt, "resumed": resumed, "seconds": seconds,
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S")}
    atomic_write_text(os.path.join(run_dir, DONE_FILE), dumps(done, indent=2) + "\n")


def _last_line(path: str, offset: int) -> str:
    """Last non-empty line written to ``path`` after ``offset`` (the attempt's error message)."""
    try:
        with open(path, "rb") as fh:
            fh.seek(offset)
            text = fh.read()[-8192:].decode(errors="replace")
    except OSError:
        return ""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1][:500] if lines else ""
