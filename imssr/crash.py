"""Native crashes leave a trace: a Python traceback on stderr and in the directory being written.

A segmentation fault in a native library ends the process before any Python code can run.
:mod:`faulthandler` writes the traceback to one file descriptor: while a process holds run directories for writing, a
pipe to a small shell process in a session of its own (a terminal's Ctrl-C leaves it alone), which after a crash copies
the report to stderr and appends it to ``crash.log`` in each directory; otherwise stderr alone.
"""
from __future__ import annotations

import faulthandler
import os
import signal
import subprocess
import threading
from typing import Optional

CRASH_LOG = "crash.log"
"""The file in a run directory (or a sweep root) that a native crash's traceback is appended to."""

# Reads the whole pipe (EOF comes when the writer exits, however it exits), then writes what it
# read, if anything, to stderr and to every log named as an argument.
_COPY = 'report=$(cat); [ -n "$report" ] || exit 0; printf "%s\\n" "$report" >&2; ' \
        'for log in "$@"; do printf "%s\\n" "$report" >> "$log"; done'

_lock = threading.Lock()
_logs: list[str] = []
_reporter: Optional[tuple[subprocess.Popen, int]] = None


def report_native_crashes() -> None:
    """Report a native crash of this process on stderr (and in the crash logs of the
    directories it holds); idempotent."""
    with _lock:
        _retarget()


def add_crash_log(directory: str) -> None:
    """Append a native crash's report to ``DIRECTORY/crash.log`` as well, until
    :func:`remove_crash_log`."""
    with _lock:
        _logs.append(os.path.abspath(os.path.join(directory, CRASH_LOG)))
        _retarget()


def remove_crash_log(directory: str) -> None:
    """Stop reporting to ``DIRECTORY/crash.log`` (the directory's writer let it go)."""
    path = os.path.abspath(os.path.join(directory, CRASH_LOG))
    with _lock:
        if path in _logs:
            _logs.remove(path)
            _retarget()


def _retarget() -> None:
    global _reporter
    previous = _reporter
    _reporter = None
    if _logs:
        read, write = os.pipe()
        try:
            proc = subprocess.Popen(["sh", "-c", _COPY, "sh", *_logs], stdin=read, stdout=subprocess.DEVNULL,
                                    start_new_session=True)
        except OSError:  # no shell to copy with: stderr alone
            os.close(write)
            faulthandler.enable(file=2, all_threads=True)
        else:
            faulthandler.enable(file=write, all_threads=True)
            _reporter = (proc, write)
        finally:
            os.close(read)
    else:
        faulthandler.enable(file=2, all_threads=True)
    if previous is not None:
        proc, write = previous
        os.close(write)
        proc.wait()


def describe_exit(status: Optional[int]) -> str:
    """How a child process ended, from its exit status as :mod:`subprocess` and
    :mod:`multiprocessing` give it (minus a signal's number when a signal killed it):
    ``exit status 2``, ``killed by signal 9 (SIGKILL)``, ``killed by signal 11 (SIGSEGV, a native crash)``."""
    if status is None:
        return "no exit status yet"
    if status >= 0:
        return f"exit status {status}"
    try:
        name = signal.Signals(-status).name
    except ValueError:
        return f"killed by signal {-status}"
    native = ", a native crash" if -status in _NATIVE_CRASHES else ""
    return f"killed by signal {-status} ({name}{native})"


_NATIVE_CRASHES = {signal.SIGSEGV, signal.SIGBUS, signal.SIGILL, signal.SIGFPE, signal.SIGABRT}
