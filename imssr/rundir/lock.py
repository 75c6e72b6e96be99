"""One writer per directory: an exclusive lock on a run directory or a sweep root.

``DIR/.imssr.lock`` holds the owner's PID (and host); the lock itself is ``flock`` on that
file, which the kernel drops when the process exits however it exits (kill -9 included), so
a lock file left by a dead process is simply taken over.  A second writer fails at once with
"DIR is in use by PID n".  Readers (``imssr evaluate``, ``imssr report``) take no lock: every
file they read is replaced atomically.

Release unlinks the file while still holding the lock; a process that opened the old file
just before and locks it just after notices that the path no longer leads to the file it
locked, and tries again.  On NFS, Linux implements ``flock`` with byte-range locks that the
server sees, so runs on several nodes of a shared file system exclude each other too.
"""
from __future__ import annotations

import errno
import fcntl
import os
import socket
import time
from typing import Optional

from imssr.crash import add_crash_log, remove_crash_log
from imssr.errors import ImssrError
from imssr.files import disk_full_as_error, open_own

LOCK_FILE = ".imssr.lock"


class DirectoryLock:
    """Exclusive lock on ``directory`` (created if missing), held until :meth:`release`.

    Directories that :meth:`acquire` created are removed again on release while they are
    empty (a run refused before it wrote anything leaves nothing behind).
    """

    def __init__(self, directory: str):
        self.directory = directory
        self.path = os.path.join(directory, LOCK_FILE)
        self._fd: Optional[int] = None
        self._created: list[str] = []

    def acquire(self) -> "DirectoryLock":
        d = self.directory
        if os.path.exists(d) and not os.path.isdir(d):
            raise ImssrError(f"{d} is a file, not a directory")
        self._created = _missing_dirs(d)
        os.makedirs(d, exist_ok=True)
        try:
            for _ in range(100):
                with disk_full_as_error(self.path):
                    fd = open_own(self.path, os.O_RDWR | os.O_CREAT)
                try:
                    _flock_exclusive(fd)
                except OSError as exc:
                    owner = _owner(fd)
                    os.close(fd)
                    if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                        raise ImssrError(f"{d} is in use by {owner}; wait for it to finish or stop it") from None
                    if exc.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                        print(f"imssr: warning: {d} is on a file system without file locks; "
                              "nothing stops a second process from writing to it", flush=True)
                        return self
                    raise
                try:
                    same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
                except FileNotFoundError:
                    same = False
                if not same:  # released (and unlinked) by its owner between our open and flock
                    os.close(fd)
                    continue
                try:
                    with disk_full_as_error(self.path):
                        os.ftruncate(fd, 0)
                        os.write(fd, f"{os.getpid()} {socket.gethostname()}\n".encode())
                except BaseException:
                    os.close(fd)
                    raise
                self._fd = fd
                add_crash_log(d)  # the writer's native crash, if any, lands beside what it wrote
                return self
            raise ImssrError(f"could not lock {d}: its lock file keeps changing")
        except BaseException:
            self._remove_created()
            raise

    def release(self) -> None:
        """Give the lock up (idempotent)."""
        if self._fd is not None:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass
            os.close(self._fd)
            self._fd = None
            remove_crash_log(self.directory)
        self._remove_created()

    def _remove_created(self) -> None:
        for path in reversed(self._created):
            try:
                os.rmdir(path)
            except OSError:  # not empty: the run wrote something, keep it
                break
        self._created = []

    def __enter__(self) -> "DirectoryLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


# RunDir.in_use() (a status probe) holds a shared lock for a few microseconds; a writer that
# meets one waits this long before it calls the directory busy.
_PROBE_WAIT_S, _PROBE_TRIES = 0.02, 10


def _flock_exclusive(fd: int) -> None:
    """``flock(LOCK_EX | LOCK_NB)``, tried again for up to 0.2 s while another process holds
    the lock: a writer holds it for its whole run, a probe only for an instant."""
    for attempt in range(_PROBE_TRIES):
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES) or attempt == _PROBE_TRIES - 1:
                raise
            time.sleep(_PROBE_WAIT_S)


def _missing_dirs(directory: str) -> list[str]:
    """``directory`` and those of its parents that do not exist, outermost first."""
    missing = []
    path = os.path.abspath(directory)
    while not os.path.exists(path):
        missing.append(path)
        parent = os.path.dirname(path)
        if parent == path:
            break
        path = parent
    return missing[::-1]


def _read_owner(fd: int) -> tuple[Optional[int], str]:
    """The PID and host the lock file names; (None, "") before its owner wrote them."""
    try:
        text = os.pread(fd, 200, 0).decode(errors="replace").split()
    except OSError:
        text = []
    if not text or not text[0].isdigit():
        return None, ""
    return int(text[0]), text[1] if len(text) > 1 else ""


def _owner(fd: int) -> str:
    """"PID n" (and "on HOST" when another machine holds it) from the lock file."""
    pid, host = _read_owner(fd)
    if pid is None:
        return "another process"  # it has the lock but has not written its PID yet
    return f"PID {pid}" + (f" on {host}" if host and host != socket.gethostname() else "")


def held_by(directory: str) -> Optional[tuple[Optional[int], str]]:
    """Whether a process holds ``directory``'s lock now (a shared lock tried for an instant):
    None when none does, else the PID and host its lock file names (PID None before its owner
    wrote it).  Held, the PID cannot be a recycled one."""
    try:
        fd = os.open(os.path.join(directory, LOCK_FILE), os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as exc:
        return _read_owner(fd) if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES) else None
    finally:
        os.close(fd)
    return None


def local_holder(directory: str) -> Optional[int]:
    """The PID of the process on this machine that holds ``directory``'s lock now; None when
    no process holds it, one on another machine does, or its owner has not written its PID."""
    owner = held_by(directory)
    return owner[0] if owner is not None and owner[1] == socket.gethostname() else None
