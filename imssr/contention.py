"""CPU contention: how many cores other processes keep busy, and which of them yield to this one.

A training warns when its torch threads would contend with busy cores (:func:`contention_warning`). Processes that
yield the CPU to this one do not count: those :data:`YIELDING_NICE` or more nice levels below it, within what they
compete inside of, an autogroup or a CPU cgroup (:func:`scheduling_group`), which ``imssr sweep`` reads as well. The
readings are Linux's ``/proc``: elsewhere the 1-minute load average alone decides.
"""
from __future__ import annotations

import os
import time
from typing import Callable, Optional

from imssr.files import read_small


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
    return (read_small("/proc/sys/kernel/sched_autogroup_enabled") or "").strip() == "1"


def autogroup(pid: int | str = "self") -> Optional[tuple[str, int]]:
    """(name, nice) of the autogroup of process ``pid`` from ``/proc/PID/autogroup``; None when
    it has none (the boot-time group, whose file is empty) or the file cannot be read."""
    try:
        name, _, nice = (read_small(f"/proc/{pid}/autogroup") or "").split()
        return name, int(nice)
    except ValueError:
        return None


def _v2_has_cpu(path: str) -> Optional[bool]:
    """Whether the cgroup v2 group at ``path`` has the cpu controller (None: unknown)."""
    text = read_small(f"/sys/fs/cgroup{path.rstrip('/')}/cgroup.controllers")
    return None if text is None else "cpu" in text.split()


def parse_cpu_cgroup(text: str, has_cpu: Callable[[str], Optional[bool]] = _v2_has_cpu) -> str:
    """The cgroup whose CPU share a process runs under, from its ``/proc/PID/cgroup`` text: the path in the v1 ``cpu``
    hierarchy; else, under cgroup v2, the deepest group of its path that has the ``cpu`` controller (``has_cpu(path)``;
    a group without it shares its parent's); "/" when none does or it cannot be told (the kernel's root group)."""
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
    text = read_small(f"/proc/{pid}/cgroup")
    return None if text is None else parse_cpu_cgroup(text)


def scheduling_group(pid: int | str = "self", autogroups: Optional[bool] = None
                     ) -> Optional[tuple[str, Optional[int]]]:
    """What process ``pid`` competes for the CPU inside of: its autogroup ``(name, nice)`` under autogroup
    scheduling (``autogroups``; None: read it) in the root CPU cgroup; ``("cgroup:PATH", None)`` in a CPU cgroup
    (which competes by its weight); None when it competes as a task on its own."""
    group = cpu_cgroup(pid)
    if group not in (None, "/"):
        return f"cgroup:{group}", None
    if group == "/" and (autogroup_scheduling() if autogroups is None else autogroups):
        return autogroup(pid)
    return None


def yields_to(task_nice: int, group: Optional[tuple[str, Optional[int]]], own_nice: int,
              own_group: Optional[tuple[str, Optional[int]]]) -> bool:
    """Whether a process of nice value ``task_nice`` in scheduling group ``group`` yields the CPU
    to one of ``own_nice`` in ``own_group``: inside one group the tasks' nice values compare,
    across groups the groups' (across CPU cgroups the weights decide: taken to contend)."""
    if group is not None and own_group is not None and group[0] == own_group[0]:
        return task_nice - own_nice >= YIELDING_NICE
    theirs = group[1] if group is not None else task_nice
    ours = own_group[1] if own_group is not None else own_nice
    return theirs is not None and ours is not None and theirs - ours >= YIELDING_NICE


def _proc_stat(pid: int | str) -> Optional[tuple[int, int]]:
    """(user + system clock ticks of all its threads, nice value) of process ``pid``."""
    text = read_small(f"/proc/{pid}/stat")
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
    ran = {pid: stat[1] for pid, stat in stats_after.items() if pid in stats_before and stat[0] > stats_before[pid][0]}
    left_out = yielding_pids(ran)
    left_before = {pid: stats_before[pid][0] for pid in left_out}
    left_after = {pid: stats_after[pid][0] for pid in left_out}
    if own_before is not None and own_after is not None:
        left_before[os.getpid()], left_after[os.getpid()] = own_before[0], own_after[0]
    return others_busy_cores(before, after, os.cpu_count() or 1, left_before, left_after)


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity: a cgroup's or ``taskset``'s), else the machine's."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def contention_warning(threads: int, load: float | None = None, cores: int | None = None) -> str | None:
    """A one-line warning if ``threads`` torch threads would contend with other busy processes:
    torch's intra-op pool spins on every thread, and a 2-thread update on a busy 2-core machine was measured many times
    slower than with 1.  ``load``: the cores other processes keep busy, the smaller of the 1-minute load average and a
    0.2 s look (a job that just ended does not count); ``cores``: the usable cores (both read when None)."""
    if threads <= 1:
        return None
    if cores is None:
        cores = usable_cores()
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
