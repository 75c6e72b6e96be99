"""Small helpers shared across the package: atomic files, seeding, thread contention."""
from __future__ import annotations

import contextlib
import csv
import errno
import os
import random
import re
import secrets
import time
from typing import Iterable, Iterator, Optional

import numpy as np
import torch

from imssr.errors import ImssrError


@contextlib.contextmanager
def atomic_path(path: str, needed: Optional[int] = None) -> Iterator[str]:
    """Yield a temporary path beside ``path``; on success, fsync and rename it over ``path``.

    A reader never sees a half-written file: it sees the old file or the new one.  The
    temporary file is created with mode ``0o666`` so that the process umask decides the
    final permissions, as for any file the user creates (``tempfile.mkstemp`` would make
    every output private, 0600).  A full disk (``ENOSPC``, a quota, a short write) becomes
    one :func:`no_space_message` line naming ``path`` and ``needed`` bytes (when given);
    the old file stays in place and the temporary file is removed.
    """
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
    """One line: "no space left on DEVICE while writing PATH (N MB needed)"."""
    try:
        device = mount_point(os.path.dirname(os.path.abspath(path)))
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
    """Turn a full-disk ``OSError`` raised inside the block into an :class:`ImssrError`."""
    try:
        yield
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        raise ImssrError(no_space_message(path, needed, quota=exc.errno == errno.EDQUOT)) from None


def atomic_write_text(path: str, text: str) -> None:
    with atomic_path(path, needed=len(text.encode())) as tmp:
        with open(tmp, "w") as fh:
            fh.write(text)


def read_csv(path: str) -> list[dict]:
    """The rows of a CSV file with a header, as dicts (none if the file does not exist)."""
    if not os.path.exists(path):
        return []
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def atomic_write_csv(path: str, header: list[str], rows: Iterable[list]) -> str:
    """Write ``header`` and ``rows`` as CSV atomically; returns ``path``."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            writer.writerows(rows)
    return path


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def rng_states() -> dict:
    """The global Python, numpy and torch RNG states, in types that ``torch.load(weights_only=True)``
    reads (plain containers and tensors): a checkpoint then never needs pickled numpy objects."""
    return {"python": random.getstate(), "numpy": random_state_to_plain(np.random.get_state()),
            "torch": torch.get_rng_state()}


def set_rng_states(states: dict) -> None:
    random.setstate(states["python"])
    np.random.set_state(random_state_from_plain(states["numpy"]))
    torch.set_rng_state(states["torch"])


def random_state_to_plain(state: tuple) -> dict:
    """A ``np.random.RandomState.get_state()`` tuple as a dict of plain values (the MT19937 key
    as a list of ints), so that a checkpoint holding it loads with ``weights_only=True``."""
    name, key, pos, has_gauss, gauss = state
    return {"bit_generator": str(name), "key": [int(k) for k in key], "pos": int(pos),
            "has_gauss": int(has_gauss), "gauss": float(gauss)}


def random_state_from_plain(state) -> tuple:
    """The ``RandomState.set_state`` tuple of :func:`random_state_to_plain`'s dict; a tuple (as
    checkpoints of imssr 0.x hold it) passes through."""
    if not isinstance(state, dict):
        return state
    return (state["bit_generator"], np.asarray(state["key"], dtype=np.uint32), state["pos"],
            state["has_gauss"], state["gauss"])


def _cpu_times() -> Optional[tuple[int, int]]:
    """(idle, total) jiffies of all CPUs from ``/proc/stat`` (Linux), or None."""
    try:
        with open("/proc/stat", encoding="ascii") as fh:
            fields = [int(v) for v in fh.readline().split()[1:9]]  # user .. steal, no guest time
    except (OSError, ValueError):
        return None
    return (fields[3] + fields[4], sum(fields)) if len(fields) >= 5 else None


def busy_cores(before: tuple[int, int], after: tuple[int, int], ncpu: int) -> float:
    """Cores kept busy between two :func:`_cpu_times` readings of a machine with ``ncpu`` CPUs."""
    idle, total = after[0] - before[0], after[1] - before[1]
    return 0.0 if total <= 0 else ncpu * (1.0 - idle / total)


def busy_cores_now(interval_s: float = 0.2) -> Optional[float]:
    """Cores that other processes keep busy now (this process sleeps while it looks), or None."""
    before = _cpu_times()
    if before is None:
        return None
    time.sleep(interval_s)
    after = _cpu_times()
    return None if after is None else busy_cores(before, after, os.cpu_count() or 1)


def contention_warning(threads: int, load: float | None = None, cores: int | None = None) -> str | None:
    """A one-line warning if ``threads`` torch threads would contend with other busy processes.

    torch's intra-op pool spins on every thread; when the cores are already busy
    (another run, a test suite) a 2-thread update on a 2-core machine was measured
    running many times slower than with 1 thread.  ``load`` is how many cores other processes
    keep busy and ``cores`` the usable cores (both read from the OS when None): the smaller of
    the 1-minute load average and the cores busy during a 0.2 s look at ``/proc/stat``, so that
    a job that ended seconds ago (``scripts/setup.sh`` before ``imssr demo``) does not count.
    """
    if threads <= 1:
        return None
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    if load is None:
        try:
            load = os.getloadavg()[0]
        except OSError:  # not available on this platform
            return None
        if load + threads > cores + 0.5:  # only then is the 0.2 s look worth taking
            now = busy_cores_now()
            if now is not None:
                load = min(load, now)
    if load + threads <= cores + 0.5:
        return None
    return (f"imssr: warning: other processes keep {load:.1f} of {cores} cores busy and this run uses "
            f"{threads} torch threads; "
            "threads that contend with other processes can run many times slower "
            "(set --set train.torch_threads=1, or stop the other jobs)")
