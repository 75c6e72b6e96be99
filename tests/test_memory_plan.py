"""The memory plan of a training (:mod:`imssr.training.memory`): what every run of a batch will
hold, reckoned before anything is built or written, refused in one line with the arithmetic."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from conftest import tiny_config
from imssr.cli import main
from imssr.presets import make_config
from imssr.replay import FrameReplayBuffer, available_memory_bytes, choose_replay_device
from imssr.training import entry
from imssr.training.memory import auto_margin, replay_slots, run_needs

resource = pytest.importorskip("resource")

SLOT = 30_036
"""A pendulum_swingup slot: a 100 px frame, one action, reward, discount, step in episode, two
physics coordinates and the agent step."""


def test_a_batch_that_outgrows_host_memory_is_refused_before_anything_is_written(tmp_path, capsys):
    """The paper's IM-CURL (100,000 slots a seed) in as many seeds as it takes to pass what this
    machine has available: one line with the arithmetic and the ways out, and no run directory."""
    available = available_memory_bytes()
    if available is None:
        pytest.skip("no MemAvailable in /proc/meminfo")
    seeds = available // (100_000 * SLOT) + 1
    out = tmp_path / "batch"
    assert main(["train", "--algo", "im-curl", "--task", "pendulum_swingup", "--seeds", f"1-{seeds}",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"imssr: error: {seeds:,} runs need {seeds * 100_000 * SLOT / 1e9:.1f} GB of host memory "
                          f"for replay (100,000 slots x {SLOT:,} B each) and ")
    assert err.endswith(" GB is available: train fewer seeds at once, lower train.replay_capacity, or put the "
                        "frames on disk with --set train.replay_device=disk\n")
    assert len(err.splitlines()) == 1 and not out.exists()


def test_a_run_counts_the_slots_its_budget_fills_and_the_buffers_bytes_per_slot():
    """A budget shorter than the capacity fills a slot per agent step and one per episode; a slot
    holds what :class:`FrameReplayBuffer` holds for the task (its action and physics state)."""
    from imssr.envs import make_env

    cfg = tiny_config("curl", steps=250)  # two episodes of 125 agent steps
    assert replay_slots(cfg) == 250 + 2 + 1
    cfg.train.replay_capacity = 100
    assert replay_slots(cfg) == 100
    for task in ("cartpole_swingup_sparse", "walker_walk"):
        env = make_env(task)
        try:
            buf = FrameReplayBuffer(10, (3, 100, 100), env.action_space.shape[0], physics_dim=env.physics_state_dim)
        finally:
            env.close()
        needs = run_needs(make_config("curl", task))
        assert needs.frame_bytes + needs.other_bytes == buf.bytes_per_slot()


def test_the_frames_of_a_batch_go_on_the_gpu_only_when_all_of_them_fit_beside_its_agents():
    """``auto`` on a GPU with 36 GB free: one run's 3 GB of frames fit, and so do 5 runs' 15 GB
    beside the other members' agents; 10 runs' 30 GB do not, though they would with a run's 4 GB
    margin alone, and each run checked alone would fit."""
    needs = run_needs(make_config("im-curl", "pendulum_swingup"))
    gpu, free = torch.device("cuda", 0), 36 * 10**9
    frames = needs.capacity * needs.frame_bytes
    placed = [choose_replay_device("auto", gpu, n * frames, free, margin_nbytes=auto_margin(needs, n)).device
              for n in (1, 5, 10)]
    assert placed == [gpu, gpu, torch.device("cpu")]
    assert 10 * frames + auto_margin(needs, 1) <= free and frames + auto_margin(needs, 1) <= free


def test_planning_many_seeds_merges_one_config(monkeypatch):
    """1000 seeds of one config: the preset is merged and validated once, each seed's config is
    a copy with its own seed."""
    calls = []
    real = entry.run_config
    monkeypatch.setattr(entry, "run_config", lambda *a, **kw: calls.append(1) or real(*a, **kw))
    planned = entry.plan(entry.TrainRequest(algo="im-curl", task="pendulum_swingup", seeds=list(range(1000)),
                                            out="batch", values={"train.steps": 1000}))
    assert len(calls) == 1
    assert [p.config.train.seed for p in planned] == list(range(1000))
    assert {p.config.train.steps for p in planned} == {1000}
    assert planned[7].run.path == os.path.join("batch", "seed_7")
    assert planned[7].config.to_dict() == {**planned[0].config.to_dict(),
                                          "train": {**planned[0].config.to_dict()["train"], "seed": 7}}


def test_frames_on_disk_are_checked_against_the_free_space_of_their_file_system(tiny_fs, tmp_path, capsys):
    """``train.replay_device=disk``: two runs whose frames (1,009 slots of 30,000 B each: 1,000
    agent steps in 8 episodes) outgrow a small file system are refused in one line before either
    directory is made."""
    mount = tiny_fs("20m")
    out = os.path.join(mount, "batch")
    assert main(["train", "--algo", "curl", "--task", "cartpole_swingup_sparse", "--seeds", "1,2", "--out", out,
                 "--steps", "1000", "--set", "train.replay_device=disk"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("imssr: error: 2 runs need 0.1 GB of disk for replay frames (1,009 slots x 30,000 B each); ")
    assert f"is free on the file system of {mount}: free some space" in err and len(err.splitlines()) == 1
    assert os.listdir(mount) == []


def test_an_address_space_limit_is_counted_for_the_whole_replay(tmp_path):
    """Under ``ulimit -v`` the replay's arrays are mapped at their capacity whatever the budget: 4
    runs of 100,000 slots (12 GB) under an 8 GiB limit are refused in one line naming the limit."""
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (8 * 2**30, resource.RLIM_INFINITY))

    proc = subprocess.run([sys.executable, "-m", "imssr", "train", "--algo", "curl", "--task", "pendulum_swingup",
                           "--seeds", "1-4", "--out", str(tmp_path / "batch"), "--steps", "100"],
                          preexec_fn=limit, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    assert proc.returncode == 2, proc.stderr[-3000:]
    err = proc.stderr.strip()
    assert err.startswith(f"imssr: error: 4 runs need {4 * 100_000 * SLOT / 1e9:.1f} GB of address space for replay "
                          "(100,000 slots each) and "), err
    assert "this process's address-space limit (ulimit -v) is 8.00 GiB: raise it (ulimit -v unlimited), or train " \
           "fewer seeds at once, lower train.replay_capacity" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "batch").exists()


def test_a_run_counts_its_environments_and_renderers_beside_replay_and_agent(tmp_path):
    """Small networks and a short budget make replay and agents small; the rest of each run (its
    environments and renderers, RUN_HOST_BYTES) is what a large batch of them cannot hold."""
    from imssr.errors import ImssrError
    from imssr.rundir import RunDir
    from imssr.training.memory import RUN_HOST_BYTES, memory_plan

    available = available_memory_bytes()
    if available is None:
        pytest.skip("no MemAvailable in /proc/meminfo")
    cfg = tiny_config("curl", "cartpole_swingup")
    needs = run_needs(cfg)
    n = available // RUN_HOST_BYTES + 1
    # Replay and agents alone would fit: what refuses the batch is the runs' own memory.
    assert n * (needs.frames_bytes + needs.others_bytes + needs.agent_bytes + needs.activation_bytes) < available
    with pytest.raises(ImssrError, match=rf"^{n:,} runs need .* and {n * RUN_HOST_BYTES / 1e9:.1f} GB for their "
                                         rf"environments and renderers \(140 MB a run\); .* GB is available"):
        memory_plan([cfg] * n, [RunDir(str(tmp_path / f"seed_{i}")) for i in range(n)])


def test_a_thousand_small_seeds_are_refused_before_any_directory(tmp_path, capsys):
    """`--seeds 1-1000` of small networks, frames and replay: refused in one line with the
    arithmetic before the first run directory is made."""
    available = available_memory_bytes()
    if available is None or available > 1000 * 140e6:
        pytest.skip("a machine with room for 1,000 runs")
    out = tmp_path / "batch"
    assert main(["train", "--algo", "curl", "--task", "cartpole_swingup", "--steps", "250", "--seeds", "1-1000",
                 "--set", "agent.hidden_dim=32", "--set", "agent.encoder_filters=8", "--set", "env.image_size=64",
                 "--set", "agent.crop_size=56", "--set", "train.replay_capacity=5000", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("imssr: error: 1,000 runs need ") and len(err.strip().splitlines()) == 1, err
    assert "GB for their environments and renderers (140 MB a run)" in err and "train fewer seeds at once" in err
    assert not out.exists()
