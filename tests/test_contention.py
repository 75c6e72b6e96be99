"""imssr.contention: the thread-contention warning and which processes yield to this one."""
import os

import pytest

from imssr.contention import (YIELDING_NICE, busy_cores, busy_cores_now, contention_warning, cpu_cgroup,
                              others_busy_cores, parse_cpu_cgroup, scheduling_group, yielding_pids, yields_to)
from imssr.sweep.runner import start_training


@pytest.mark.parametrize("threads, load, cores, warns", [
    (2, 0.1, 2, False),   # idle machine: both threads have a core
    (2, 1.0, 2, True),    # another job holds a core
    (2, 2.3, 2, True),    # e.g. a test suite beside the run
    (1, 5.0, 2, False),   # one thread never spins against itself
    (4, 1.0, 8, False),   # plenty of free cores
])
def test_contention_warning(threads, load, cores, warns):
    message = contention_warning(threads, load=load, cores=cores)
    assert (message is not None) == warns
    if warns:
        assert "\n" not in message and "train.torch_threads=1" in message


def test_busy_cores_reads_the_share_of_non_idle_time():
    # (idle, total) jiffies: 2 CPUs, 100 jiffies each elapsed, 150 of the 200 idle -> half a core busy
    assert busy_cores((1000, 4000), (1150, 4200), ncpu=2) == pytest.approx(0.5)
    assert busy_cores((1000, 4000), (1000, 4200), ncpu=2) == pytest.approx(2.0)
    assert busy_cores((1000, 4000), (1000, 4000), ncpu=2) == 0.0  # no time passed


@pytest.mark.skipif(not os.path.exists("/proc/stat"), reason="Linux only")
def test_busy_cores_now_is_a_share_of_the_machine():
    now = busy_cores_now(0.05)
    assert now is not None and 0.0 <= now <= (os.cpu_count() or 1) + 1e-9


@pytest.mark.parametrize("task_nice, group, own_nice, own_group, yields", [
    (19, None, 0, None, True),                               # no autogroups: task nice values compare
    (5, None, 0, None, False),
    (19, ("/autogroup-2", 0), 0, ("/autogroup-1", 0), False),  # `nice -n 19` in another session: it does not yield
    (0, ("/autogroup-2", 19), 0, ("/autogroup-1", 0), True),   # a session niced by a sweep
    (19, ("/autogroup-1", 0), 0, ("/autogroup-1", 0), True),   # the same session: task nice values compare
    (19, ("/autogroup-2", 19), 10, ("/autogroup-1", 10), False),  # 9 levels below a niced caller
    (15, None, 0, ("/autogroup-1", 0), True),                # a task of the boot-time group against a session
    (19, ("cgroup:/user.slice/b", None), 0, ("cgroup:/user.slice/a", None), False),  # cgroup weights decide
    (19, ("cgroup:/a", None), 0, ("cgroup:/a", None), True),  # inside one cgroup, nice values compare
    (0, ("/autogroup-2", 19), 0, ("cgroup:/a", None), False),
])
def test_which_processes_yield_to_this_one(task_nice, group, own_nice, own_group, yields):
    assert yields_to(task_nice, group, own_nice, own_group) == yields


def test_time_of_processes_left_out_is_not_busy():
    # 2 CPUs, 200 ticks elapsed, 40 idle: 1.6 cores busy, of which 100 ticks (1 core) by PID 7
    left = others_busy_cores((1000, 4000), (1040, 4200), 2, {7: 500, 8: 10}, {7: 600, 9: 50})
    assert left == pytest.approx(0.6)  # PID 8 ended and PID 9 started inside the look: not left out
    assert others_busy_cores((1000, 4000), (1000, 4200), 2, {7: 0}, {7: 400}) == 0.0  # never below 0


V2_CPU = {"/user.slice", "/user.slice/user-0.slice", "/system.slice"}.__contains__  # which v2 groups have cpu


@pytest.mark.parametrize("text, group", [
    ("12:cpu,cpuacct:/docker/abc\n11:memory:/docker/abc\n0::/docker/abc", "/docker/abc"),  # v1 cpu wins
    ("4:cpuset:/x\n3:cpuacct:/y\n0::/", "/"),                              # cpuset, cpuacct are not cpu
    ("0::/user.slice/user-0.slice/session-3.scope", "/user.slice/user-0.slice"),  # v2: deepest with cpu
    ("0::/init.scope", "/"),                                                # v2: no group with cpu
    ("0::/", "/"),
    ("1:name=systemd:/a\n0::/user.slice/x", "/user.slice"),                # hybrid, cpu on the v2 side
    ("1:cpu:/\n0::/user.slice/x", "/"),                                     # hybrid, cpu on v1 at the root
])
def test_which_cgroup_holds_a_processs_cpu_share(text, group):
    assert parse_cpu_cgroup(text, V2_CPU) == group


@pytest.mark.skipif(not os.path.exists("/proc/self/cgroup"), reason="Linux cgroups only")
def test_this_process_competes_in_a_known_way():
    group = scheduling_group()
    assert cpu_cgroup().startswith("/")
    assert group is None or group[0].startswith(("/autogroup-", "cgroup:/"))


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="Linux /proc only")
@pytest.mark.skipif(os.nice(0) > 19 - YIELDING_NICE, reason="a process cannot be niced 10 levels below this one")
def test_a_niced_sweeps_training_is_not_contention_a_plain_job_is():
    """A process started as a `nice -n 19 imssr sweep` starts its trainings (task and session
    niced) yields to this one; a process at normal priority does not."""
    with open(os.devnull, "w") as log:
        niced = start_training(["nice", "-n", "19", "sleep", "30"], log, dict(os.environ), niceness=19)
        plain = start_training(["sleep", "30"], log, dict(os.environ), niceness=None)
    try:
        yielding = yielding_pids({niced.pid: 19, plain.pid: 0, os.getpid(): 0})
        assert niced.pid in yielding and plain.pid not in yielding and os.getpid() not in yielding
    finally:
        for proc in (niced, plain):
            proc.kill()
            proc.wait()
