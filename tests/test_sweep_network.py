"""What a sweep's private local Ray opens to the network: every socket that any process of the
sweep listens on is bound to loopback while the sweep resumes, finishes and then skips a run, and
the sweep's output carries Ray's warnings but not Ray's notices."""
import ipaddress
import os
import re
import resource
import signal
import subprocess
import sys
import time

from conftest import SWEEP_TINY, sweep_status
from imssr.errors import INTERRUPTED_EXIT
from imssr.rundir import SWEEP_LOG, RunDir
from imssr.sweep.grid import SweepConfig, expand

TASK = "cartpole_swingup_sparse"
# Updates from agent step 10 on and one evaluation, at the end of a 40-step budget: a run
# stopped near its start has something to resume and to train, in a few seconds.
TINY = SWEEP_TINY + ["train.seed_steps=10", "train.eval_every_steps=40"]


def sweep_command(root, *args):
    return [sys.executable, "-m", "imssr", "sweep", "--no-progress", "--root", str(root), "--algos", "curl",
            "--tasks", TASK, *args, *[a for o in TINY for a in ("--set", o)]]


# -- the sockets of a process tree (/proc) ------------------------------------------------------

def _descendants(root_pid: int) -> dict[int, str]:
    """``root_pid`` and every process below it: pid -> command name."""
    children: dict[int, list[int]] = {}
    names: dict[int, str] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                stat = fh.read()
        except OSError:  # ended meanwhile
            continue
        # "pid (comm) state ppid ...": comm may hold spaces and parentheses.
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        ppid = int(stat[stat.rindex(")") + 2:].split()[1])
        names[int(entry)] = name
        children.setdefault(ppid, []).append(int(entry))
    tree, todo = {}, [root_pid]
    while todo:
        pid = todo.pop()
        if pid in names:
            tree[pid] = names[pid]
            todo.extend(children.get(pid, []))
    return tree


def _socket_inodes(pid: int) -> set[int]:
    inodes = set()
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return inodes
    for fd in fds:
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(int(target[8:-1]))
    return inodes


def _address(hex_address: str) -> ipaddress._BaseAddress:
    """An address as /proc/net/tcp* writes it: 32-bit words in host (little-endian) order."""
    raw = bytes.fromhex(hex_address)
    return ipaddress.ip_address(b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4)))


def _listening() -> dict[int, str]:
    """Every listening socket of this network namespace: inode -> ``address:port``.  TCP sockets
    in LISTEN, and UDP sockets bound without a peer (they take datagrams from anyone)."""
    found = {}
    for table, state in (("tcp", "0A"), ("tcp6", "0A"), ("udp", "07"), ("udp6", "07")):
        with open(f"/proc/net/{table}") as fh:
            next(fh)
            for line in fh:
                cols = line.split()
                local, remote, st, inode = cols[1], cols[2], cols[3], int(cols[9])
                if st != state or (table.startswith("udp") and int(remote.split(":")[0], 16)):
                    continue
                host, port = local.split(":")
                found[inode] = f"{_address(host)}:{int(port, 16)}"
    return found


def _is_loopback(address: str) -> bool:
    ip = ipaddress.ip_address(address.rsplit(":", 1)[0])
    mapped = getattr(ip, "ipv4_mapped", None)  # ::ffff:127.0.0.1, an IPv4 socket on a dual-stack one
    return ip.is_loopback or (mapped is not None and mapped.is_loopback)


def watch_listeners(proc: subprocess.Popen, timeout: float) -> dict[tuple[int, str], set[str]]:
    """Until ``proc`` ends: every socket that ``proc`` or a process below it listens on,
    ``(pid, command name) -> {address:port}``, sampled a few times a second."""
    seen: dict[tuple[int, str], set[str]] = {}
    deadline = time.monotonic() + timeout
    while proc.poll() is None:
        assert time.monotonic() < deadline, "the sweep did not end"
        listening = _listening()
        for pid, name in _descendants(proc.pid).items():
            for inode in _socket_inodes(pid) & listening.keys():
                seen.setdefault((pid, name), set()).add(listening[inode])
        time.sleep(0.2)
    return seen


# -- the tests -----------------------------------------------------------------------------------

def _interrupted(run, cfg) -> int:
    """``run`` trained by ``imssr train`` and stopped by SIGTERM once its training loop began (its
    train.csv), as a user's Ctrl-C leaves it: a checkpoint of the step it stopped at, which it
    returns.  Its budget is far beyond the sweep's, so that the stop always comes first."""
    config = run.resolved_config(cfg)
    config.train.steps = 5000
    path = RunDir(run.dir).write_config(config)
    proc = subprocess.Popen([sys.executable, "-m", "imssr", "train", "--no-progress", "--config", path,
                             "--out", run.dir], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 300
        while not os.path.exists(os.path.join(run.dir, "train.csv")):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[0]
            time.sleep(0.1)
        proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=120)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == INTERRUPTED_EXIT, out
    return int(re.search(r"stopped at agent step (\d+) by SIGTERM", out).group(1))


def test_a_local_ray_sweep_listens_on_loopback_only_and_still_resumes_and_skips(tmp_path):
    """One run, interrupted beforehand: the sweep's own Ray resumes and finishes it while every
    listening socket of the sweep's processes (the driver, GCS, raylet, agents, workers, the
    training) is watched; the same command then starts nothing."""
    root = tmp_path / "sweep"
    cfg = SweepConfig(root=str(root), algos=["curl"], tasks=[TASK], seeds=[1], steps=40, overrides=TINY)
    (run,) = expand(cfg)
    assert _interrupted(run, cfg) < 40

    command = sweep_command(root, "--seeds", "1", "--steps", "40")
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        seen = watch_listeners(proc, timeout=300)
        out = proc.communicate()[0]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    beyond = {f"{name} ({pid})": sorted(a for a in addresses if not _is_loopback(a))
              for (pid, name), addresses in seen.items()}
    assert not {k: v for k, v in beyond.items() if v}, f"listening beyond loopback: {beyond}"
    # Not a vacuous pass: Ray's servers, the driver's and a worker's were among those watched.
    names = {name for _, name in seen}
    assert {"gcs_server", "raylet"} <= names, seen
    assert any(pid == proc.pid for pid, _ in seen), seen  # the driver's core worker
    assert any(name.startswith("ray::") for name in names), seen  # a worker or an agent

    (status,) = sweep_status(root)["runs"]
    assert (status["action"], status["state"], status["attempts"], status["final_step"]) == \
        ("resume", "done", 1, 40), out
    with open(os.path.join(run.dir, SWEEP_LOG)) as fh:
        assert "(resume)" in fh.read()
    again = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "all 1 runs are done; nothing to start" in again.stdout, \
        again.stdout + again.stderr


def test_a_local_sweeps_output_keeps_rays_warnings_and_not_its_notices(tmp_path):
    """Under a file-descriptor limit Ray calls too low (a warning that asks for `ulimit -n`), a
    local sweep whose one attempt fails at once (a folder where its sweep.log goes): the output
    holds imssr's lines and Ray's warning, and nothing of Ray's that asks nothing of the user (the
    token-authentication notice)."""
    root = tmp_path / "sweep"
    (run,) = expand(SweepConfig(root=str(root), algos=["curl"], tasks=[TASK], seeds=[2]))
    os.makedirs(os.path.join(run.dir, SWEEP_LOG))
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    limit = min(2048, soft if hard == resource.RLIM_INFINITY else hard)

    def low_limit():
        resource.setrlimit(resource.RLIMIT_NOFILE, (limit, limit))

    env = {k: v for k, v in os.environ.items() if k != "RAY_AUTH_MODE"}  # the mode left to imssr and Ray
    proc = subprocess.run(sweep_command(root, "--seeds", "2", "--steps", "20", "--retries", "0"),
                          capture_output=True, text=True, timeout=300, env=env, preexec_fn=low_limit)
    assert proc.returncode == 1, proc.stdout + proc.stderr  # the run failed
    lines = (proc.stdout + proc.stderr).splitlines()
    ray_lines = [line for line in lines if not line.startswith(("imssr:", "FAILED "))]
    assert len(ray_lines) == 1 and f"File descriptor limit {limit} is too low" in ray_lines[0], lines
    assert not any("Token authentication" in line for line in lines), lines


def test_a_process_that_imported_ray_first_gets_a_one_line_error(tmp_path):
    """Ray reads the setting that keeps it on loopback when it is imported: a process that
    imported ray before the sweep could set it is refused, before anything is written."""
    root = tmp_path / "sweep"
    script = ("import sys, ray\nfrom imssr.cli import main\n"
              f"sys.exit(main({sweep_command(root, '--seeds', '1', '--steps', '20')[3:]!r}))\n")
    env = {k: v for k, v in os.environ.items() if k != "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"}
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "imssr: error: a local sweep keeps Ray on loopback, which needs RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 "
        "before ray is imported, but this process imported ray without it: set it in the environment"]
    assert not root.exists()
