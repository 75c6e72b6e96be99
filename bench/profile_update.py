"""Where one agent update's time goes: torch.profiler over a few updates, top operators.

    python bench/profile_update.py [--algo im-curl] [--batch 128] [--updates 4] [--set agent.update_schedule=fused]

Paper preset of ``--algo`` (``--set`` overrides as ``imssr train``), a replay
buffer of random frames, 2 warm-up updates, then ``--updates`` profiled ones;
prints operators by self CPU time and the seconds per update.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile

import imssr  # noqa: F401
from imssr.agents import make_agent
from imssr.config import apply_overrides
from imssr.presets import make_config
from imssr.replay import FrameReplayBuffer


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--algo", default="im-curl")
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--updates", type=int, default=4)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--rows", type=int, default=15)
    p.add_argument("--set", action="append", default=[])
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    cfg = make_config(a.algo, "cartpole_swingup_sparse")
    cfg.agent.batch_size = a.batch
    if cfg.aux.name != "soda":  # SODA keeps its own batch of 256
        cfg.aux.batch_size = a.batch
    cfg = apply_overrides(cfg, a.set).validate()
    rng = np.random.default_rng(0)
    buf = FrameReplayBuffer(700, (3, 100, 100), 1, seed=0)
    buf.add_first(rng.integers(0, 256, (3, 100, 100), dtype=np.uint8))
    for _ in range(600):
        buf.add(rng.uniform(-1, 1, 1), 0.0, 1.0, rng.integers(0, 256, (3, 100, 100), dtype=np.uint8))
    agent = make_agent((9, 100, 100), 1, cfg.agent, cfg.aux, cfg.intrinsic)
    for s in range(2):
        agent.update(buf, s)
    t0 = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for s in range(2, 2 + a.updates):
            agent.update(buf, s)
    elapsed = time.perf_counter() - t0
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=a.rows))
    print(f"{a.algo} {' '.join(a.set)}: {elapsed / a.updates:.3f} s/update under the profiler "
          f"(batch {a.batch}, {a.threads} threads)")


if __name__ == "__main__":
    main()
