"""The prepared GPU commands on the CPU at tiny sizes: scripts/gpu_seeds.sh (the correctness check,
every layout's rate, the profile, one seed alone) and scripts/gpu_results.sh (the results lease);
few files, at most two folders deep (what a device run brings back)."""
from __future__ import annotations

import os
import subprocess
import sys

from conftest import REPO


def run_script(name: str, out, **env) -> tuple[subprocess.CompletedProcess, list[str]]:
    """``scripts/NAME`` on the CPU at tiny sizes, with this test's Python and no folder of packages
    to install (tests/test_gpu_bundle.py installs one); it must succeed and leave what a device
    run brings back: at most 8 files under ``out``, at most one folder deep.  Returns the process
    and those files' paths relative to ``out``, sorted."""
    proc = subprocess.run(["bash", os.path.join(REPO, "scripts", name)],
                          env={**os.environ, "OUT": str(out), "TINY": "1", "DEVICE": "cpu", "PYTHON": sys.executable,
                               "GPU_BUNDLE": os.path.join(str(out), "no-bundle"), **env},
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    files = sorted(os.path.relpath(os.path.join(d, f), out) for d, _, fs in os.walk(out) for f in fs)
    assert len(files) <= 8 and all(f.count(os.sep) <= 1 for f in files), files
    return proc, files


def test_the_prepared_seeds_command_works_on_the_cpu(tmp_path):
    out = tmp_path / "out"
    proc, files = run_script("gpu_seeds.sh", out)
    assert files == ["seeds/alone.txt", "seeds/check.txt", "seeds/device.txt", "seeds/profile.txt",
                     "seeds/seeds_fast.csv", "seeds/seeds_fast.md", "seeds/seeds_paper.csv", "seeds/seeds_paper.md"]
    assert "stopped" not in proc.stdout and "no time left" not in proc.stdout
    seeds = out / "seeds"
    check = (seeds / "check.txt").read_text()
    assert "1 passed" in check and "needs a GPU" in check  # the CPU test ran, the GPU ones skipped
    rows = [line.split(" | ")[:2] for line in (seeds / "seeds_paper.md").read_text().splitlines()
            if line.startswith("| 1 |") or line.startswith("| 2 |")]
    assert rows == [["| 1", "1 process, members"], ["| 1", "1 process, members, graphs"],
                    ["| 1", "1 process, members in turn, graphs"], ["| 2", "2 processes"],
                    ["| 2", "1 process, members"], ["| 2", "1 process, members, graphs"],
                    ["| 2", "1 process, members in turn, graphs"]], rows
    csv_rows = (seeds / "seeds_paper.csv").read_text().splitlines()
    assert len(csv_rows) == 1 + len(rows) and csv_rows[0].startswith("n,layout,")
    assert "| 2 | 1 process, members, graphs |" in (seeds / "seeds_fast.md").read_text()
    profile = (seeds / "profile.txt").read_text()
    assert "overlap: kernel time / wall time = " in profile and "| fp32 |" in profile and "| bf16 |" in profile
    alone = (seeds / "alone.txt").read_text()
    assert "curl:agent.cuda_graphs=true" in alone and "wait for the device" in alone


def test_the_prepared_results_lease_works_on_the_cpu(tmp_path):
    # A plan whose one run is committed: the lease trains nothing and says so; device.txt holds
    # what a run's provenance records (the lease itself: tests/test_lease_results.py).
    from conftest import make_run

    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "sweep.json").write_text(
        '{"algos": ["curl"], "tasks": ["cartpole_swingup"], "seeds": "1", "steps": 250}')
    (tmp_path / "plan.json").write_text('{"steps": [{"sweep": "t/sweep.json", "runs": "t/runs"}]}')
    make_run(str(tmp_path / "t" / "runs"), "curl", 1, [("training", 250, 10.0)], task="cartpole_swingup", steps=250)
    out = tmp_path / "out"
    proc, files = run_script("gpu_results.sh", out, PLAN=str(tmp_path / "plan.json"), BUDGET_S="120")
    assert files == ["results/device.txt", "results/lease.md", "results/train.log"], proc.stdout + proc.stderr
    assert "0 run(s) started" in (out / "results" / "lease.md").read_text()
    assert "nothing to train" in proc.stdout
    device = (out / "results" / "device.txt").read_text()
    for field in ("imssr", "git_commit", "python", "torch", "cuda", "nvidia_driver", "numpy", "dm_control", "mujoco"):
        assert f"\n{field}: " in device, device
