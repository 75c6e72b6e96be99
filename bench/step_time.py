"""Seconds per training step (one env step + every update of that agent step), same process.

    python bench/step_time.py [--task cartpole_swingup_sparse] [--steps 100] [--threads 2]
        [--variants im-curl curl "im-curl:agent.channels_last=false"] [--device cpu]
        [--baseline-rev GIT_REV] [--bf16 curl im-curl soda im-soda pad svea]

Each variant is ``ALGO[:SECTION.FIELD=VALUE,...]`` with the paper's preset for
``ALGO`` and the overrides applied; ``rev:ALGO[:...]`` runs it with the code of
``--baseline-rev`` (exported by ``git archive`` and imported under another
name), so an optimisation is measured against the earlier code in the same
process.  The first variant is the baseline of the printed ratios.  Every variant gets its own environment and a replay buffer
seeded with ``--seed-steps`` random-action steps of real rendered frames; then
the variants take one training step each in turn (act, all updates, env step,
replay add), so machine noise hits them alike.  Prints the median and mean
over ``--steps`` steps after ``--warmup``, and the process's peak RSS.  On
CUDA every step ends with a synchronisation so that queued kernels are counted.
``--bf16 ALGO ...`` runs, for each ALGO, its preset at ``agent.precision=fp32`` and at
``bf16`` (after any ``--variants``) and prints the ratio bf16 / fp32 of each pair (median and
mean: SODA's auxiliary update runs every other step), against a target of 0.6.
Each variant's line is followed by its step's split (medians): the action, the update's issue,
the environment's step and the wait for the device after it; on CUDA the environment steps while
the device runs the update, so a wait near zero means the device is not the limit.
Each variant samples from the replay store its training would use on ``--device``
(``train.replay_device`` resolved as the trainer does, for the preset's replay capacity), and
each line says which.  Timings never go in tests.
"""
from __future__ import annotations

import argparse
import importlib
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import imssr  # noqa: F401  (sets the GL backend)
from imssr.config import apply_overrides
from imssr.envs import make_env
from imssr.presets import make_config
from imssr.replay import FrameReplayBuffer, make_replay_buffer, replay_placement
from imssr.training.build import build_agent, resolve_device


def import_revision(rev: str):
    """The package as of git revision ``rev``, importable as ``imssr_rev``."""
    root = Path(__file__).resolve().parent.parent
    dest = Path(tempfile.mkdtemp(prefix="imssr_rev_"))
    tar = subprocess.run(["git", "-C", str(root), "archive", rev, "imssr"], check=True,
                         capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=tar, check=True)
    (dest / "imssr").rename(dest / "imssr_rev")
    for f in (dest / "imssr_rev").rglob("*.py"):
        text = f.read_text()
        f.write_text(text.replace("from imssr.", "from imssr_rev.").replace("import imssr.", "import imssr_rev.")
                     .replace("from imssr import", "from imssr_rev import"))
    sys.path.insert(0, str(dest))
    return {m: importlib.import_module(f"imssr_rev.{m}")
            for m in ("config", "envs", "presets", "replay", "training.build")}


class Runner:
    """One variant: its environment, replay and agent, stepped like the training loop."""

    def __init__(self, spec: str, task: str, seed_steps: int, device, batch: int, rev=None):
        algo, _, overrides = spec.partition(":")
        api = {"make_config": make_config, "apply_overrides": apply_overrides, "make_env": make_env,
               "FrameReplayBuffer": FrameReplayBuffer, "build_agent": build_agent}
        if algo == "rev":
            if rev is None:
                raise SystemExit("a rev: variant needs --baseline-rev")
            algo, _, overrides = overrides.partition(":")
            api = {"make_config": rev["presets"].make_config, "apply_overrides": rev["config"].apply_overrides,
                   "make_env": rev["envs"].make_env, "FrameReplayBuffer": rev["replay"].FrameReplayBuffer,
                   "build_agent": rev["training.build"].build_agent}
        cfg = api["make_config"](algo, task)
        if batch:
            cfg.agent.batch_size = batch
        cfg = api["apply_overrides"](cfg, [o for o in overrides.split(",") if o])
        self.spec, self.cfg, self.device = spec, cfg, device
        self.env = api["make_env"](task, seed=0, action_repeat=cfg.env.action_repeat,
                                   shadow_size=cfg.env.shadow_size)
        obs, info = self.env.reset(seed=0)
        capacity, action_dim = seed_steps + 2000, self.env.action_space.shape[0]
        if spec.startswith("rev:"):
            self.replay_store = "host (the revision's FrameReplayBuffer)"
            self.replay = api["FrameReplayBuffer"](capacity, info["frame"].shape, action_dim,
                                                   frame_stack=cfg.env.frame_stack, seed=0)
        else:
            # The store training would use: train.replay_device resolved for the preset's
            # capacity, as the trainer resolves it, built at the bench's smaller capacity.
            frame = info["frame"]
            placement = replay_placement(cfg.train.replay_device, device,
                                         cfg.train.replay_capacity * frame.size, cfg.train.gpu_share)
            self.replay_store = replay_store_text(placement.device)
            self.replay = make_replay_buffer(placement.device, capacity, frame.shape, action_dim,
                                             frame_stack=cfg.env.frame_stack, seed=0)
        self.replay.add_first(info["frame"])
        self.obs = obs
        self.rng = np.random.default_rng(0)
        for _ in range(seed_steps):
            self._env_step(self.rng.uniform(-1, 1, self.env.action_space.shape).astype(np.float32))
        self.agent = api["build_agent"](cfg, obs.shape, self.env.action_space.shape[0], device)
        self.step = seed_steps
        self.times: list[float] = []
        self.warmup_times: list[float] = []
        self.splits: list[tuple[float, float, float, float]] = []
        """Per recorded step: the action (its copy to the host waits for the device), the
        update's issue (on CUDA the host queues its kernels and goes on), the environment's
        step (on CUDA while the device runs the update), the wait for the device after it."""

    def _env_step(self, action) -> None:
        self.obs, reward, terminated, truncated, info = self.env.step(action)
        self.replay.add(action, reward, 0.0 if terminated else 1.0, info["frame"])
        if terminated or truncated:
            self.obs, info = self.env.reset()
            self.replay.add_first(info["frame"])

    def train_step(self, record: bool) -> None:
        t0 = time.perf_counter()
        action = self.agent.act(self.obs, deterministic=False)
        t1 = time.perf_counter()
        self.agent.update(self.replay, self.step)
        t2 = time.perf_counter()
        self._env_step(action)
        t3 = time.perf_counter()
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        t4 = time.perf_counter()
        self.step += 1
        (self.times if record else self.warmup_times).append(t4 - t0)
        if record:
            self.splits.append((t1 - t0, t2 - t1, t3 - t2, t4 - t3))


def replay_store_text(device: torch.device) -> str:
    """Which replay store a variant samples from, in words."""
    if device.type == "cpu":
        return "host (numpy frames; batches copied to the agent's device)"
    return f"{device} (tensor frames gathered and cropped there)"


def run_interleaved(runners, warmup: int, steps: int) -> None:
    """``warmup`` then ``steps`` recorded training steps of every runner, one step each in turn,
    so that machine noise (and the GPU's clocks) hit every variant alike."""
    for i in range(warmup + steps):
        for r in runners:
            r.train_step(record=i >= warmup)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="cartpole_swingup_sparse")
    p.add_argument("--variants", nargs="+", default=["curl", "im-curl"])
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--seed-steps", type=int, default=300)
    p.add_argument("--batch", type=int, default=0, help="RL batch size (0: the preset's, 128)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="cpu")
    p.add_argument("--baseline-rev", default=None, help="git revision that rev:ALGO variants run")
    p.add_argument("--bf16", nargs="*", default=[], metavar="ALGO",
                   help="also run each ALGO at agent.precision=fp32 and bf16 and print their ratios")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    device = resolve_device(a.device)
    rev = import_revision(a.baseline_rev) if a.baseline_rev else None
    pairs = [(f"{algo}:agent.precision=fp32", f"{algo}:agent.precision=bf16") for algo in a.bf16]
    specs = [*(a.variants if not pairs or "--variants" in sys.argv else []), *(s for pair in pairs for s in pair)]
    runners = [Runner(v, a.task, a.seed_steps, device, a.batch, rev) for v in specs]
    run_interleaved(runners, a.warmup, a.steps)
    base = statistics.median(runners[0].times)
    print(f"task {a.task}, {a.steps} steps after {a.warmup} warm-up, {a.threads} threads, device {device}")
    for r in runners:
        med, mean = statistics.median(r.times), statistics.fmean(r.times)
        print(f"{r.spec:45s} median {med:.3f} s/step  mean {mean:.3f}  ratio to {runners[0].spec}: "
              f"{med / base:.3f}  replay: {r.replay_store}")
        act, issue, env, wait = (statistics.median(part) * 1e3 for part in zip(*r.splits))
        print(f"{'':45s} split (median ms): act {act:.1f}, update issued {issue:.1f}, environment {env:.1f}, "
              f"wait for the device {wait:.1f}")
    by_spec = {r.spec: r for r in runners}
    if pairs:
        print("bf16 / fp32 of the whole training step, same process (target: <= 0.6)")
    for fp32, bf16 in pairs:
        f, b = by_spec[fp32].times, by_spec[bf16].times
        ratio_med = statistics.median(b) / statistics.median(f)
        ratio_mean = statistics.fmean(b) / statistics.fmean(f)
        print(f"{fp32.split(':')[0]:12s} fp32 median {statistics.median(f):.3f} s  bf16 median "
              f"{statistics.median(b):.3f} s  ratio median {ratio_med:.3f}  mean {ratio_mean:.3f}")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB (all variants)")


if __name__ == "__main__":
    main()
