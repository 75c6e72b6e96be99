"""Files written whole or not at all, and the errors of a full disk.

:func:`atomic_path` and its writers (:func:`atomic_write_text`, :func:`atomic_write_csv`) let a
reader see the old file or the new one, never half of one; a full disk or a spent quota is one
:class:`~imssr.errors.ImssrError` line naming the file (:func:`disk_full_as_error`).  Files appended to in place (logs)
are opened by :func:`open_append`, which refuses a symbolic link (:func:`open_own`); :func:`read_csv` reads a log back.
"""
from __future__ import annotations

import contextlib
import csv
import errno
import io
import os
import re
import secrets
from typing import Iterable, Iterator, Optional, TextIO

from imssr.errors import ImssrError


@contextlib.contextmanager
def atomic_path(path: str, needed: Optional[int] = None) -> Iterator[str]:
    """Yield a temporary path beside ``path``; on success, fsync and rename it over ``path``, so
    a reader sees the old file or the new one.  The temporary file's mode is ``0o666`` less the
    umask, as for any file the user creates (``tempfile.mkstemp`` would make it 0600).  A full disk
    is one :func:`no_space_message` line naming ``path`` and ``needed`` bytes; the old file stays."""
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    tmp = _create_temp(directory, os.path.basename(path))
    try:
        with disk_full_as_error(path, needed):
            yield tmp
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


TEMP_GLOB = ".tmp-*"
"""The names of :func:`atomic_path`'s temporary files: ``.tmp-<8 hex digits>-<name>``."""
_TEMP_NAME = re.compile(r"\.tmp-[0-9a-f]{8}-(.+)")


def temp_file_target(name: str) -> Optional[str]:
    """The file name that the temporary file ``name`` of :func:`atomic_path` was to replace, or
    None when ``name`` is not such a file."""
    match = _TEMP_NAME.fullmatch(name)
    return match.group(1) if match else None


def _create_temp(directory: str, name: str) -> str:
    """Create an empty ``.tmp-*`` file in ``directory`` (mode 0o666 less the umask)."""
    for _ in range(100):
        tmp = os.path.join(directory, f".tmp-{secrets.token_hex(4)}-{name}")
        try:
            with disk_full_as_error(os.path.join(directory, name)):
                fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(errno.EEXIST, "no free temporary file name", directory)


# numpy's ``tofile`` reports a short write as "N requested and M written", without errno.
_SHORT_WRITE = re.compile(r"\d+ requested and \d+ written")


def is_disk_full(exc: BaseException) -> bool:
    """``exc`` says the file system is full (or the user's quota is spent)."""
    return isinstance(exc, OSError) and (exc.errno in (errno.ENOSPC, errno.EDQUOT)
                                         or bool(_SHORT_WRITE.search(str(exc))))


def mount_point(path: str) -> str:
    """The mount point of the file system that holds ``path`` (or its nearest existing parent)."""
    path = os.path.realpath(path)
    while not os.path.exists(path):
        path = os.path.dirname(path)
    while not os.path.ismount(path):
        path = os.path.dirname(path)
    return path


def no_space_message(path: str, needed: Optional[int] = None, quota: bool = False) -> str:
    """One line: "no space left on DEVICE while writing PATH (N MB needed)"; ``path`` is the file
    written, or the directory written into (TensorBoard's ``tb/``, which may be a mount of its own)."""
    try:
        device = mount_point(path if os.path.isdir(path) else os.path.dirname(os.path.abspath(path)))
    except OSError:  # pragma: no cover - the directory vanished meanwhile
        device = "its device"
    what = "no space left (disk quota exceeded)" if quota else "no space left"
    size = "" if needed is None else f" ({_mb(needed)} MB needed)"
    return f"{what} on {device} while writing {path}{size}"


def _mb(nbytes: int) -> str:
    mb = nbytes / 1e6
    return f"{mb:.1f}" if mb >= 0.1 else f"{max(mb, 0.001):.3f}"


@contextlib.contextmanager
def disk_full_as_error(path: str, needed: Optional[int] = None) -> Iterator[None]:
    """Turn a full-disk ``OSError`` raised inside the block into an :class:`ImssrError`, and a
    write past the process's file-size limit (``EFBIG``: ``ulimit -f``) into one naming the file."""
    try:
        yield
    except OSError as exc:
        if exc.errno == errno.EFBIG:
            size = "" if needed is None else f" ({_mb(needed)} MB needed)"
            raise ImssrError(f"file larger than this process's file-size limit (ulimit -f: "
                             f"{_fsize_limit()}) while writing {path}{size}") from None
        if not is_disk_full(exc):
            raise
        raise ImssrError(no_space_message(path, needed, quota=exc.errno == errno.EDQUOT)) from None


def _fsize_limit() -> str:
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    except (ImportError, OSError, ValueError):  # pragma: no cover - not POSIX
        return "unknown"
    return "unlimited" if soft == resource.RLIM_INFINITY else f"{_mb(soft)} MB"


def read_small(path: str) -> Optional[str]:
    """A small file's text (a /proc or /sys file; bytes that are not UTF-8 replaced), or None when
    it cannot be read."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            return fh.read()
    except OSError:
        return None


def atomic_write_text(path: str, text: str) -> None:
    with atomic_path(path, needed=len(text.encode())) as tmp:
        with open(tmp, "w") as fh:
            fh.write(text)


OWN_FILE_RULE = "imssr writes only to a file of its own there (remove the link)"
"""What :func:`open_own` says of a symbolic link by default (a file opened for writing)."""


def open_own(path: str, flags: int, rule: str = OWN_FILE_RULE) -> int:
    """``os.open(path, flags | O_NOFOLLOW | O_CLOEXEC, 0o666)``; a symbolic link there is refused
    in one line, "PATH is a symbolic link; RULE": a link planted in a shared directory would make
    a run write into a file outside it, or read one from elsewhere into its results."""
    try:
        return os.open(path, flags | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ImssrError(f"{path} is a symbolic link; {rule}") from None
        raise


def open_append(path: str, newline: Optional[str] = None) -> TextIO:
    """``path`` opened for appending text (created if missing); a link is refused (:func:`open_own`)."""
    return os.fdopen(open_own(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT), "a", newline=newline)


def read_csv(path: str, complete_only: bool = False) -> list[dict]:
    """The rows of a CSV file with a header, as dicts (none if the file does not exist).
    ``complete_only``: leave out a last row without its line end, which a killed writer cut
    short (``...,training,2.`` of ``2.5`` would read as a number)."""
    if not os.path.exists(path):
        return []
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            text = fh.read()
    except UnicodeDecodeError as exc:
        raise ImssrError(f"{path} is damaged: not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset "
                         f"{exc.start})") from None
    if complete_only and text and not text.endswith("\n"):
        text = text[:text.rfind("\n") + 1]
    return list(csv.DictReader(io.StringIO(text, newline="")))


def atomic_write_csv(path: str, header: list[str], rows: Iterable[list]) -> str:
    """Write ``header`` and ``rows`` as CSV atomically; returns ``path``."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            writer.writerows(rows)
    return path
