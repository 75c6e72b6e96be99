"""bench/profile_seeds.py, bench/replay_checkpoint.py, bench/replay_disk.py, bench/floor.py and
bench/pixels_speed.py on tiny CPU smoke runs: they run and print their tables (never timings);
the seeds bench runs in tests/test_gpu_script.py."""
import os
import subprocess
import sys

from conftest import REPO, TINY_NETWORKS, tiny_overrides, tiny_sets

TINY = tiny_sets(TINY_NETWORKS)


def _run(script, *args):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([REPO, os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, os.path.join(REPO, "bench", script), *args], capture_output=True,
                          text=True, env=env, cwd=REPO, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


def test_profile_seeds_profiles_a_single_agent_and_each_mode():
    out = _run("profile_seeds.py", "--n", "2", "--modes", "members", "turn+graphs", "--steps", "1", "--warmup", "1",
               "--fill", "100", "--threads", "1", "--rows", "3", *TINY)
    headings = [line for line in out.splitlines() if line.startswith("## ")]
    assert [h.split(":")[0] for h in headings] == ["## 1 seed, single", "## 2 seeds, members",
                                                   "## 2 seeds, turn+graphs"]
    assert all("CPU operators busy" in h for h in headings) and "aten::" in out


def test_floor_counts_flops_and_the_bytes_each_operator_moves():
    sys.path.insert(0, os.path.join(REPO, "bench"))
    try:
        import floor
    finally:
        sys.path.remove(os.path.join(REPO, "bench"))
    import torch

    a, b = torch.ones(100), torch.ones(100)
    with floor.ByteCounter() as moved:
        c = a + b                       # reads 800 bytes, writes 400
        c.view(10, 10).t()              # views move nothing
        c.add_(1)                       # in place: reads and writes c
        torch.arange(1000.0)[torch.tensor([3, 5])]  # a gather reads the rows it returns
        d = torch.empty(100)            # an allocation moves nothing
        torch.div(a, 2.0, out=d)        # an out= tensor is written, not read
    assert (moved.read, moved.written) == (800 + 400 + 8 + 16 + 400, 400 + 400 + 4000 + 8 + 400)
    out = _run("floor.py", "--precisions", "fp32", "--threads", "1", "--fill", "20", *TINY)
    row = next(line for line in out.splitlines() if line.startswith("| fp32 |")).split(" | ")
    assert float(row[1]) > 0 and float(row[4]) > 0


def test_replay_checkpoint_compares_new_frames_with_whole_rewrites(tmp_path):
    out = _run("replay_checkpoint.py", "--capacity", "50", "--frames", "130", "--every", "20", "--size", "8",
               "--dir", str(tmp_path))
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("| whole") or line.startswith("| new")]
    assert [r[0] for r in rows] == ["| whole buffer", "| new frames only"] and rows[0][3] == "1.00"
    assert float(rows[1][3]) < 1  # fewer bytes written: no timing is checked


def test_the_seeds_benches_build_their_agents_with_the_overrides():
    sys.path.insert(0, os.path.join(REPO, "bench"))
    try:
        import seeds
    finally:
        sys.path.remove(os.path.join(REPO, "bench"))
    import torch

    args = seeds.main.__globals__["argparse"].Namespace(
        algo="curl", task="cartpole_swingup", action_dim=1, fill=20, device="cpu", layout="members",
        set=[*tiny_overrides(TINY_NETWORKS), "agent.fused_adam=true"])
    batch, replays, _ = seeds.build(args, [1, 2])
    assert [m.cfg.batch_size for m in batch.members] == [8, 8] and batch.members[0].cfg.encoder_filters == 8
    assert all(g["fused"] for m in batch.members for g in m.critic_opt.param_groups) and len(replays) == 2
    # Each member is its seed's agent as a run of that seed builds it, and the seeds differ.
    args.layout = "single"
    alone, _, _ = seeds.build(args, [2])
    weights = [m.state_dict()["nets"] for m in (*batch.members, alone)]
    assert all(torch.equal(weights[1][k], weights[2][k]) for k in weights[1])
    assert not all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


SYSTEM_PATHS = ("/tmp/", "/dev/null", "/usr/bin/env", "/proc/", "/path/for/", "/usr/share/glvnd/", "/etc/glvnd/",
                "/usr/local/nvidia/")
"""The absolute paths a script may name: temporary and system files (glvnd's EGL vendor files, and
where NVIDIA's container runtime mounts the driver), and the placeholder of its usage."""


def test_scripts_and_benches_name_no_directory_of_a_particular_machine():
    """They find the repository, its .venv and their data relative to themselves (or as arguments)
    and speak of the project: an absolute path elsewhere is one machine's layout, and words about
    the machine a script was written on mean nothing to a user."""
    import glob
    import re

    path = re.compile(r"(?<![\w.~$}/:])/[A-Za-z][\w.-]*(?:/[\w.*-]+)*")
    machine = re.compile(r"\blent\b|device README|this machine|\bsession\b", re.IGNORECASE)
    found = {}
    for name in sorted(glob.glob(os.path.join(REPO, "scripts", "*")) + glob.glob(os.path.join(REPO, "bench", "*"))):
        if os.path.isfile(name):
            with open(name) as fh:
                text = fh.read()
            bad = [p for p in path.findall(text) if not (p + "/").startswith(SYSTEM_PATHS)] + machine.findall(text)
            if bad:
                found[os.path.relpath(name, REPO)] = bad
    assert not found


def test_replay_disk_compares_frames_on_disk_with_frames_in_memory(tmp_path):
    out = _run("replay_disk.py", "--capacity", "300", "--steps", "5", "--batch", "8", "--size", "8", "--reps", "1",
               "--dir", str(tmp_path))
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("| host") or line.startswith("| file")]
    assert [r[0] for r in rows] == ["| host memory (cpu)", "| file on disk (disk)"] and rows[0][2] == "1.00 |"
    assert os.listdir(tmp_path) == []  # the frames file is removed


def test_pixels_speed_compares_one_pass_with_three_in_both_layouts():
    out = _run("pixels_speed.py", "--batch", "2", "--reps", "1", "--threads", "1")
    lines = [line for line in out.splitlines() if "ratio" in line]
    assert [line.split("float32 ")[1].split(":")[0] for line in lines] == ["channels_last", "contiguous"]
