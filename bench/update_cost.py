"""Cost of one agent update: a base against its intrinsic-reward variants, same process.

    python bench/update_cost.py [--base curl] [--variants im] [--batch 128] [--steps 30] [--threads 2]

``--base`` is curl, soda, pad or svea (paper presets); ``--variants`` any of
``im,rnd,re3`` (im-X, X+rnd, X+re3).  Prints the median seconds per update of
each algorithm, interleaved step by step so machine noise hits all alike, and
each variant's ratio to the base.  Timings never go in tests.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

import imssr  # noqa: F401
from imssr.agents import make_agent
from imssr.presets import make_config
from imssr.replay import FrameReplayBuffer


def filled(n=600, seed=0):
    rng = np.random.default_rng(seed)
    buf = FrameReplayBuffer(n + 10, (3, 100, 100), 1, seed=seed)
    buf.add_first(rng.integers(0, 256, (3, 100, 100), dtype=np.uint8))
    for _ in range(n):
        buf.add(rng.uniform(-1, 1, 1), 0.0, 1.0, rng.integers(0, 256, (3, 100, 100), dtype=np.uint8))
    return buf


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--form", default="authors", choices=["authors", "training"],
                   help="intrinsic.form of the IM- variant (authors: no extra encoder pass for IM-CURL)")
    p.add_argument("--base", default="curl", choices=["curl", "soda", "pad", "svea"])
    p.add_argument("--variants", default="im", help="comma list of im, rnd, re3")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    names = {"im": f"im-{a.base}", "rnd": f"{a.base}+rnd", "re3": f"{a.base}+re3"}
    algos = [a.base] + [names[v.strip()] for v in a.variants.split(",") if v.strip()]
    agents = {}
    for algo in algos:
        cfg = make_config(algo, "cartpole_swingup_sparse")
        cfg.agent.batch_size = a.batch
        if not cfg.aux.own_batch:  # tasks trained on the RL batch
            cfg.aux.batch_size = a.batch
        cfg.intrinsic.form = a.form
        agents[algo] = (make_agent((9, 100, 100), 1, cfg.agent, cfg.aux, cfg.intrinsic), filled())
    times = {k: [] for k in agents}
    for step in range(a.steps + 3):
        for name, (agent, buf) in agents.items():
            t0 = time.perf_counter()
            agent.update(buf, step)
            if step >= 3:  # warm-up
                times[name].append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in times.items()}
    for k, v in med.items():
        print(f"{k:10s} median {v:.3f} s/update (batch {a.batch}, {a.threads} threads)")
    for k in algos[1:]:
        print(f"ratio {k} / {a.base} = {med[k] / med[a.base]:.3f}"
              + (f" (intrinsic form: {a.form})" if a.base in ("curl", "soda") and k.startswith("im-") else ""))


if __name__ == "__main__":
    main()
