"""One sweep run on a worker: ``imssr train`` as a subprocess, and the run's done marker.

The training runs in its own process so that a run cannot leak memory, threads or GL contexts into the next one, and
so that killing it (Ctrl-C on the sweep, a cancelled Ray task) leaves only its last atomic checkpoint behind, from
which the next attempt resumes.
"""
from __future__ import annotations

import ctypes
import errno
import os
import random
import signal
import subprocess
import sys
import time
from typing import Optional

from imssr.contention import scheduling_group
from imssr.crash import describe_exit
from imssr.errors import DIVERGED_PREFIX, INTERRUPTED_EXIT, ImssrError
from imssr.files import disk_full_as_error, open_append
from imssr.rundir import DIVERGED, FAILED, FINISHED, INTERRUPTED, RunDir, as_run_dir

STOP_GRACE_S = 30
"""Seconds a stopped training has to finish its agent step and checkpoint before SIGKILL."""
# Exit statuses of a training stopped by a signal: its own (it checkpointed), or the signal's when a
# second signal (or one before its handlers were in place) ended it; it resumes either way.
INTERRUPTED_STATUSES = (INTERRUPTED_EXIT, -signal.SIGTERM, -signal.SIGINT, 128 + signal.SIGTERM)
WRITER_WAIT_S = STOP_GRACE_S
"""Seconds an attempt waits for a process that still holds its run's lock (a training of a killed
sweep, stopping with its checkpoint) before it starts and lets the training refuse in one line."""


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    # If the Ray worker that waits on this training is killed (force-cancelled task, Ray
    # shut down), the training must not live on as an orphan holding CPUs.
    ctypes.CDLL(None).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def start_training(cmd: list[str], log, env: dict, niceness: Optional[int] = None) -> subprocess.Popen:
    """``cmd`` in a new session (so that :meth:`RunAttempt.stop` can signal its whole process
    group) writing to ``log``; on Linux it dies with its parent.  ``niceness`` > 0: the training
    runs at that priority even under autogroup scheduling (:func:`lower_session_priority`)."""
    preexec = _die_with_parent if sys.platform.startswith("linux") else None
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                            preexec_fn=preexec, start_new_session=True)
    if niceness:
        try:
            problem = lower_session_priority(proc.pid, niceness)
            if problem:
                log.write(f"imssr sweep: warning: the training runs at normal priority: {problem}\n")
                log.flush()
        except BaseException:  # interrupted (a cancelled Ray task) before the caller holds proc
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            raise
    return proc


AUTOGROUP_WAIT_S = 30.0
"""How long :func:`lower_session_priority` waits out the kernel's rate limit."""


def lower_session_priority(pid: int, niceness: int, wait_s: float = AUTOGROUP_WAIT_S) -> str:
    """Give the session of ``pid`` the nice value ``niceness`` (under autogroup scheduling a nice
    value counts only inside a session, so a training's own session would ignore ``nice -n 19
    imssr sweep``); returns what went wrong, "" when it worked or there is nothing to do.  The
    kernel takes one such change per 0.1 s machine-wide: parallel starts take turns, jittered."""
    path = f"/proc/{pid}/autogroup"
    group = scheduling_group(pid)
    if group is None or group[1] is None:
        return ""  # no autogroup applies: the inherited nice value already does
    deadline = time.monotonic() + wait_s
    while True:
        try:
            with open(path, "w") as fh:
                fh.write(str(niceness))
            return ""
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EBUSY):
                return f"cannot write {path}: {exc.strerror}"
            if time.monotonic() >= deadline:
                return f"{path} stayed busy for {wait_s:.0f} s (the kernel takes one change per 0.1 s)"
            time.sleep(random.uniform(0.1, 0.2))


class RunAttempt:
    """One attempt of a run: ``imssr train --config RUN/config.json --out RUN`` (``--resume`` when
    it has a checkpoint), or of a packed process's runs ``imssr train --runs RUN ...``, in a
    subprocess writing to the (first) run's ``sweep.log``.  ``niceness``: the nice value of the
    sweep that asked for the run (Ray workers run at +15), given to the training's session."""

    def __init__(self, run_dir: RunDir | str | list, steps: int, attempt: int, niceness: Optional[int] = None):
        self.runs = [as_run_dir(r) for r in (run_dir if isinstance(run_dir, (list, tuple)) else [run_dir])]
        self.run = run = self.runs[0]
        for r in self.runs:
            os.makedirs(r.path, exist_ok=True)
        self.steps, self.attempt = steps, attempt
        # Classified now, not when the sweep planned or when an earlier attempt began: a training
        # of a killed sweep may still be stopping here, writing the checkpoint this one resumes.
        # A packed process resumes when every run has a checkpoint; before that (a batch stopped
        # during its first one) it starts afresh, which clears what that left.
        deadline = time.monotonic() + WRITER_WAIT_S
        for r in self.runs:
            while r.in_use() and time.monotonic() < deadline:
                time.sleep(0.2)
        self.resumed = all(r.has_checkpoint() for r in self.runs)
        what = ["--config", run.config_path, "--out", run.path] if len(self.runs) == 1 else \
            ["--runs", *(r.path for r in self.runs)]
        cmd = [sys.executable, "-m", "imssr", "train", *what] + (["--resume"] if self.resumed else [])
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # One thread pool per reserved CPU (the config's train.torch_threads, which the sweep sets
        # from --cpus-per-run) for every library, not torch's alone: the default (every core) makes
        # parallel runs spin against each other, 10x slower on a shared 2-core machine.
        threads = _torch_threads(run)
        if threads:
            env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
        self.log_path = run.sweep_log
        self.start = time.time()
        self.proc: Optional[subprocess.Popen] = None
        self.error = ""
        doing = f"clear {run.path} for a fresh attempt"
        try:
            if not self.resumed:
                # An earlier attempt that failed before its first checkpoint left logs that nothing
                # continues; `imssr train` refuses to start over them, so the sweep clears them (and
                # nothing else: a finished run, a training still running there, fail the attempt).
                for r in self.runs:
                    r.discard_unresumable()
            doing = f"write {self.log_path}"
            for other in self.runs[1:]:
                _open_log(other.sweep_log, f"==> attempt {attempt}: trained in one process with "
                                           f"{len(self.runs) - 1} other run(s); its output is in {self.log_path}\n"
                          ).close()
            log = _open_log(self.log_path, f"==> attempt {attempt} ({'resume' if self.resumed else 'fresh'}) at "
                                           f"{time.strftime('%Y-%m-%d %H:%M:%S')}: {' '.join(cmd)}\n")
        except ImssrError as exc:  # a full disk, a link, a run not ours to clear: one line, nothing started
            self.error = str(exc)
            return
        except OSError as exc:  # a directory in its place, no permission
            self.error = f"cannot {doing}: {exc.strerror or exc}"
            return
        with log:
            self.offset = log.tell()
            self.proc = start_training(cmd, log, env, niceness)

    @property
    def ended(self) -> bool:
        """Whether there is nothing left to wait for: the training exited, or never started."""
        return self.proc is None or self.proc.poll() is not None

    def stop(self) -> None:
        """SIGTERM the training (its process group), SIGKILL after :data:`STOP_GRACE_S`."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()

    def _own_status(self, run: RunDir) -> Optional[dict]:
        """``run``'s status when this attempt wrote it (not one left by an earlier attempt)."""
        try:
            if os.path.getmtime(run.status_path) < self.start - 1.0:
                return None
        except OSError:
            return None
        return run.read_status()

    def finish_all(self) -> list[dict]:
        """What the finished attempt did to each of its runs (:meth:`finish` of each)."""
        return [self.finish(run) for run in self.runs]

    def finish(self, run: Optional[RunDir] = None) -> dict:
        """What the finished attempt did (see :func:`execute_runs`) to ``run`` (default: its first); writes
        ``done.json`` when the run reached its budget, even when another run of its process diverged."""
        run = run or self.run
        if self.proc is None:
            return {"ok": False, "returncode": None, "resumed": self.resumed, "error": self.error,
                    "interrupted": False, "diverged": False, "final_step": 0, "final_frame": 0, "seconds": 0.0}
        returncode = self.proc.wait()
        # In a packed process each run says how it ended (a status written by this attempt).
        own = self._own_status(run) if len(self.runs) > 1 else None
        if own is not None and own["state"] == FINISHED:
            returncode = 0  # this run finished; another of the process did not
        final_step, final_frame = run.last_evaluation()
        result = {"ok": False, "returncode": returncode, "resumed": self.resumed, "error": "",
                  "interrupted": returncode in INTERRUPTED_STATUSES and (own is None or own["state"] != DIVERGED),
                  "diverged": False, "final_step": final_step, "final_frame": final_frame,
                  "seconds": round(time.time() - self.start, 1)}
        if returncode != 0:
            error = (own or {}).get("error")
            if not error:
                # A process a signal killed said nothing of it: its last output line is not the cause.
                error = describe_exit(returncode) if returncode < 0 else _last_line(self.log_path, self.offset)
            result["error"] = error or f"exit status {returncode}"
            result["diverged"] = DIVERGED_PREFIX in result["error"]
        elif final_step < self.steps:
            result["error"] = (f"exited 0 but its last evaluation is at agent step {final_step}, "
                               f"before its budget of {self.steps} steps")
        else:
            result["ok"] = True
            run.write_done(self.steps, final_step, self.attempt, self.resumed, result["seconds"])
        if not result["ok"] and run.read_status() is None:
            # The training ended before it could say how (it failed to start, or a signal ended it
            # at once): the run's status says it here.
            state = INTERRUPTED if result["interrupted"] else DIVERGED if result["diverged"] else FAILED
            try:
                run.write_status(state, final_step, result["error"])
            except (ImssrError, OSError):  # a full disk: the result still says what happened
                pass
        return result


def execute_runs(run_dirs: list, steps: int, attempt: int, niceness: Optional[int] = None) -> list[dict]:
    """Train (or resume) the runs in ``run_dirs`` (each its ``config.json``; several in one process:
    ``imssr train --runs``) to ``steps`` agent steps and wait; one result per run (the body of a Ray task or a
    SLURM job).

    Result keys: ``ok``, ``returncode``, ``resumed``, ``error`` (the attempt's last output line when
    it failed, or ``killed by signal N (NAME)``), ``interrupted`` (stopped by a signal: resume it, it
    did not fail), ``diverged`` (a resume would diverge again from the same checkpoint: do not
    retry), ``final_step`` and ``final_frame`` (of the last evaluation), ``seconds``.  ``niceness``:
    as in :class:`RunAttempt`.
    """
    attempt_ = RunAttempt(list(run_dirs), steps, attempt, niceness)
    try:
        # In steps: a Ray cancel interrupts the main thread between bytecodes, which a
        # blocking wait for the child never returns to.
        while not attempt_.ended:
            time.sleep(0.5)
    finally:
        attempt_.stop()  # interrupted while waiting (task cancelled): nothing outlives it
    return attempt_.finish_all()


def _open_log(path: str, header: str):
    """``path`` opened for appending, ``header`` written; a full disk is one ImssrError line."""
    with disk_full_as_error(path):
        log = open_append(path)
        try:
            log.write(header)
            log.flush()
        except BaseException:
            log.close()
            raise
    return log


def _torch_threads(run: RunDir) -> int:
    """The run's ``train.torch_threads`` (0: unknown or torch's default)."""
    try:
        return run.read_config().train.torch_threads
    except (ImssrError, OSError, TypeError, ValueError):
        return 0


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
