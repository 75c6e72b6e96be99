"""Small helpers shared across the package: atomic files, seeding, thread contention."""
from __future__ import annotations

import contextlib
import csv
import errno
import io
import os
import random
import re
import secrets
import time
from typing import Callable, Iterable, Iterator, Optional, TextIO

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


def open_own(path: str, flags: int) -> int:
    """``os.open(path, flags | O_NOFOLLOW | O_CLOEXEC, 0o666)`` (the umask decides the mode of a
    new file).  A symbolic link there is refused in one line: a run directory's files are its
    own, and writing through a link planted in a shared directory would write into (or
    truncate) a file outside the run."""
    try:
        return os.open(path, flags | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ImssrError(f"{path} is a symbolic link; imssr writes only to a file of its own there "
                             "(remove the link)") from None
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
    with open(path, newline="") as fh:
        text = fh.read()
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


YIELDING_NICE = 10
"""Nice levels below this process's at which another process no longer contends with it: at 10
levels the scheduler weighs it ~1/10 (at 19, ~1/70), so this process's threads get a core as
soon as they want one (a ``nice -n 19 imssr sweep`` beside ``imssr demo``)."""


def autogroup_scheduling() -> bool:
    """Whether Linux's autogroup scheduler is on (``kernel.sched_autogroup_enabled``): CPU time
    is then shared between sessions first, and a nice value counts only inside its session."""
    try:
        with open("/proc/sys/kernel/sched_autogroup_enabled") as fh:
            return fh.read().strip() == "1"
    except OSError:
        return False


def autogroup(pid: int | str = "self") -> Optional[tuple[str, int]]:
    """(name, nice) of the autogroup of process ``pid`` from ``/proc/PID/autogroup``; None when
    it has none (the boot-time group, whose file is empty) or the file cannot be read."""
    try:
        with open(f"/proc/{pid}/autogroup") as fh:
            name, _, nice = fh.read().split()
        return name, int(nice)
    except (OSError, ValueError):
        return None


def _read(path: str) -> Optional[str]:
    """A small /proc or /sys file's text (bytes that are not UTF-8 replaced), or None."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            return fh.read()
    except OSError:
        return None


def _v2_has_cpu(path: str) -> Optional[bool]:
    """Whether the cgroup v2 group at ``path`` has the cpu controller (None: unknown)."""
    text = _read(f"/sys/fs/cgroup{path.rstrip('/')}/cgroup.controllers")
    return None if text is None else "cpu" in text.split()


def parse_cpu_cgroup(text: str, has_cpu: Callable[[str], Optional[bool]] = _v2_has_cpu) -> str:
    """The cgroup whose CPU share a process runs under, from its ``/proc/PID/cgroup`` text: the
    path in the v1 ``cpu`` hierarchy; else, under cgroup v2, the deepest group of its path that
    has the ``cpu`` controller (``has_cpu(path)``; a group without it shares its parent's);
    "/" when none does or it cannot be told (the kernel's root group)."""
    lines = [line.split(":", 2) for line in text.splitlines() if line.count(":") >= 2]
    for _, controllers, path in lines:
        if "cpu" in controllers.split(","):
            return path
    for hierarchy, controllers, path in lines:
        if hierarchy == "0" and not controllers:
            parts = [p for p in path.split("/") if p]
            for depth in range(len(parts), 0, -1):
                group = "/" + "/".join(parts[:depth])
                if has_cpu(group):
                    return group
    return "/"


def cpu_cgroup(pid: int | str = "self") -> Optional[str]:
    """:func:`parse_cpu_cgroup` of process ``pid``; None when ``/proc/PID/cgroup`` cannot be read
    (not Linux, or the process ended)."""
    text = _read(f"/proc/{pid}/cgroup")
    return None if text is None else parse_cpu_cgroup(text)


def scheduling_group(pid: int | str = "self", autogroups: Optional[bool] = None
                     ) -> Optional[tuple[str, Optional[int]]]:
    """What process ``pid`` competes for the CPU inside of, with its nice value where one applies:
    its autogroup ``(name, nice)`` under autogroup scheduling (``autogroups``; None: read it),
    which applies only to tasks of the root CPU cgroup; ``("cgroup:PATH", None)`` in a CPU
    cgroup (which competes by its cgroup weight, not by a nice value); None when it competes as
    a task on its own.  A cgroup namespace can hide a container's cgroup behind "/": then its
    tasks are taken for the root's."""
    group = cpu_cgroup(pid)
    if group not in (None, "/"):
        return f"cgroup:{group}", None
    if group == "/" and (autogroup_scheduling() if autogroups is None else autogroups):
        return autogroup(pid)
    return None


def yields_to(task_nice: int, group: Optional[tuple[str, Optional[int]]], own_nice: int,
              own_group: Optional[tuple[str, Optional[int]]]) -> bool:
    """Whether a process of nice value ``task_nice`` in scheduling group ``group`` yields the CPU
    to one of ``own_nice`` in ``own_group`` (:func:`scheduling_group`): inside one group the
    tasks' nice values compare; across groups each group competes as one, at its group's nice
    value (a task outside any group at its own); across CPU cgroups the weights decide, which
    this does not read: such a process is taken to contend."""
    if group is not None and own_group is not None and group[0] == own_group[0]:
        return task_nice - own_nice >= YIELDING_NICE
    theirs = group[1] if group is not None else task_nice
    ours = own_group[1] if own_group is not None else own_nice
    return theirs is not None and ours is not None and theirs - ours >= YIELDING_NICE


def _proc_stat(pid: int | str) -> Optional[tuple[int, int]]:
    """(user + system clock ticks of all its threads, nice value) of process ``pid``."""
    text = _read(f"/proc/{pid}/stat")
    try:
        fields = text.rpartition(")")[2].split()  # after the name: from field 3 (state) on
        return int(fields[11]) + int(fields[12]), int(fields[16])  # fields 14, 15 and 19
    except (AttributeError, ValueError, IndexError):
        return None  # ended, not readable, or not Linux's /proc


def _all_proc_stats() -> dict[int, tuple[int, int]]:
    """:func:`_proc_stat` of every process, by PID; empty where ``/proc`` is not Linux's."""
    try:
        pids = [int(e.name) for e in os.scandir("/proc") if e.name.isdigit()]
    except OSError:
        return {}
    stats = {pid: _proc_stat(pid) for pid in pids}
    return {pid: stat for pid, stat in stats.items() if stat is not None}


def yielding_pids(nice_by_pid: dict[int, int]) -> set[int]:
    """The processes among ``nice_by_pid`` (PID -> its nice value) that yield to this one
    (:func:`yields_to`); the system-wide settings are read once."""
    autogroups = autogroup_scheduling()
    own_group, own_nice = scheduling_group(autogroups=autogroups), os.nice(0)
    return {pid for pid, nice in nice_by_pid.items()
            if pid != os.getpid() and yields_to(nice, scheduling_group(pid, autogroups), own_nice, own_group)}


def others_busy_cores(before: tuple[int, int], after: tuple[int, int], ncpu: int,
                      left_out_before: dict[int, int], left_out_after: dict[int, int]) -> float:
    """:func:`busy_cores` less the CPU time that the processes in both ``left_out_*`` readings
    (PID -> clock ticks so far) took between them."""
    total = after[1] - before[1]
    if total <= 0:
        return 0.0
    left_out = sum(max(0, ticks - left_out_before[pid]) for pid, ticks in left_out_after.items()
                   if pid in left_out_before)
    return max(0.0, busy_cores(before, after, ncpu) - ncpu * left_out / total)


def busy_cores_now(interval_s: float = 0.2) -> Optional[float]:
    """Cores that other processes keep busy now, or None.  Neither this process (which reads
    ``/proc`` and sleeps while it looks) nor those that yield to it (:func:`yields_to`) count;
    only the processes that ran during the look are placed in their scheduling groups."""
    own_before = _proc_stat("self")
    before = _cpu_times()
    if before is None:
        return None
    stats_before = _all_proc_stats()
    time.sleep(interval_s)
    stats_after = _all_proc_stats()
    after = _cpu_times()
    own_after = _proc_stat("self")
    if after is None:
        return None
    ran = {pid: stat[1] for pid, stat in stats_after.items()
           if pid in stats_before and stat[0] > stats_before[pid][0]}
    left_out = yielding_pids(ran)
    left_before = {pid: stats_before[pid][0] for pid in left_out}
    left_after = {pid: stats_after[pid][0] for pid in left_out}
    if own_before is not None and own_after is not None:
        left_before[os.getpid()], left_after[os.getpid()] = own_before[0], own_after[0]
    return others_busy_cores(before, after, os.cpu_count() or 1, left_before, left_after)


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
            try:
                now = busy_cores_now()
            except (OSError, ValueError):  # an unexpected /proc: the load average decides
                now = None
            if now is not None:
                load = min(load, now)
    if load + threads <= cores + 0.5:
        return None
    return (f"imssr: warning: other processes keep {load:.1f} of {cores} cores busy and this run uses "
            f"{threads} torch threads; "
            "threads that contend with other processes can run many times slower "
            "(set --set train.torch_threads=1, or stop the other jobs)")
