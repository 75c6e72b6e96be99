"""Stopping a training on a signal: SIGTERM / SIGINT as a request to stop after the current agent
step with a checkpoint (:class:`StopRequest`), and the exception a stopped training raises."""
from __future__ import annotations

import os
import signal
import threading
from typing import Optional

from imssr.envs.worker import end_workers
from imssr.errors import INTERRUPTED_EXIT
from imssr.rundir import RunDir


class TrainingInterrupted(Exception):
    """Training stopped on a signal after checkpointing its last agent step; the message is the
    line the CLI prints ("stopped at agent step N by SIGTERM; continue with: ...")."""

    def __init__(self, message: str, step: int, out: Optional[str]):
        super().__init__(message)
        self.step = step
        """The agent step every run stopped at."""
        self.out = out
        """The ``--out`` a resume names (None: the runs have no one folder, ``--runs`` names them)."""

    def __reduce__(self):
        # Pickled across a process boundary with all three arguments (``args`` holds the message).
        return type(self), (str(self), self.step, self.out)

    @classmethod
    def at(cls, step: int, signal_name: Optional[str], run: RunDir) -> "TrainingInterrupted":
        """The training of ``run`` stopped by ``signal_name`` at agent step ``step``."""
        return cls(f"stopped at agent step {step} by {signal_name}; continue with: "
                   f"imssr train --out {run.path} --resume", step, run.path)


class StopRequest:
    """SIGTERM / SIGINT as a request to stop after the current agent step (SLURM sends SIGTERM
    on preemption and at the time limit, some seconds before SIGKILL).

    The first signal is recorded in :attr:`signal_name`; a second one stops at once.  With
    ``runs`` (the command line, which trains those run directories: one, or a batch) the second
    signal ends the process there with :data:`~imssr.errors.INTERRUPTED_EXIT` and one line,
    even in the middle of a checkpoint write: the write is atomic, so the last checkpoint stays
    whole, and the line names ``resume_command`` (default: ``--resume`` of the one run) only
    when every run has a checkpoint to continue from.  The env workers (``train.env_workers``)
    are ended with the process.  Without ``runs`` (the Python API) the default handlers come
    back: SIGTERM kills the process, SIGINT raises ``KeyboardInterrupt``.  Handlers are installed
    only on the main thread (Python's rule)."""

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self, *runs: RunDir, resume_command: Optional[str] = None):
        self.signal_name: Optional[str] = None
        self.runs = runs
        if resume_command is None and len(runs) == 1:
            resume_command = f"imssr train --out {runs[0].path} --resume"
        self.resume_command = resume_command
        """The command that continues the runs (``--out RUN --resume``, or a batch's ``--seeds`` /
        ``--runs``), which the second signal's line names."""
        self._previous: dict = {}

    def install(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            for signum in self.SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        if self.signal_name is not None:
            # A second signal that came before this handler had given way to the next: Python runs
            # it inside the first one's call (signal.signal handles what is pending first), so it
            # does here what the next handler does.
            if self.runs:
                self._exit_at_once(signum, frame)
            elif signum == signal.SIGINT:
                raise KeyboardInterrupt
            else:
                signal.signal(signum, signal.SIG_DFL)
                os.kill(os.getpid(), signum)
            return
        self.signal_name = signal.Signals(signum).name
        # os.write, not print: a signal handler may run inside a print to the same stream.
        _say(f"imssr: {self.signal_name}: stopping after this agent step with a checkpoint "
             "(a second signal stops at once)\n")
        for sig in self.SIGNALS:  # the next signal acts at once
            default = signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL
            signal.signal(sig, self._exit_at_once if self.runs else default)

    def _exit_at_once(self, signum, frame) -> None:
        """The second signal on the command line: one line and the exit, with no exception that
        could surface in a write (torch's "unexpected pos"), a ``finally`` or an exit handler."""
        _say(f"imssr: {signal.Signals(signum).name} again: {self._at_once_text()}\n")
        # os._exit skips the exit handlers, multiprocessing's too: the env workers go here.
        end_workers()
        os._exit(INTERRUPTED_EXIT)

    def _at_once_text(self) -> str:
        """What the second signal leaves: the command that continues, or why there is none."""
        without = [run.path for run in self.runs if not run.has_checkpoint()]
        if not without:
            return f"stopped at once, keeping the last checkpoint; continue with: {self.resume_command}"
        # The directories hold the logs of the runs so far, so the same command is refused.
        if len(without) == len(self.runs):
            whose = "run's" if len(self.runs) == 1 else "runs'"
            return (f"stopped at once, before the {whose} first checkpoint: nothing to resume; choose "
                    f"another --out or remove {', '.join(without)}")
        return (f"stopped at once, during the runs' first checkpoint: {', '.join(without)} "
                f"{'has' if len(without) == 1 else 'have'} none, so the runs cannot resume together; "
                f"choose another --out or remove {', '.join(run.path for run in self.runs)}")

    def uninstall(self) -> None:
        """The handlers from before :meth:`install` come back (the caller's, when ``imssr.cli.main``
        runs in a process of its own): the training, and any checkpoint write, is over."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()


def _say(text: str) -> None:
    """``text`` to stderr from a signal handler; lost when stderr is gone (a closed pipe): the
    stop goes on without its line."""
    try:
        os.write(2, text.encode())
    except OSError:
        pass
