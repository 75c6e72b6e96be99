"""Per-step cost of each test scene relative to ``training``, same process.

    python bench/scene_cost.py [--task walker_walk] [--steps 200] [--rounds 3]

One env per mode, stepped with the same random actions; modes are interleaved
in rounds so machine noise hits all alike.  Prints the median milliseconds per
agent step (physics sub-steps + scene updates + render) and the ratio to
``training``.  Timings never go in tests.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import imssr  # noqa: F401
from imssr.envs import MODES, make_env


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--task", default="walker_walk")
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--rounds", type=int, default=3)
    args = p.parse_args()
    envs = {m: make_env(args.task, seed=0, mode=m) for m in MODES}
    actions = np.random.default_rng(0).uniform(-1, 1, (args.steps,) + envs["training"].action_space.shape)
    times: dict[str, list[float]] = {m: [] for m in MODES}
    for _ in range(args.rounds):
        for mode, env in envs.items():
            env.reset()
            for a in actions:
                t0 = time.perf_counter()
                _, _, term, trunc, _ = env.step(a.astype(np.float32))
                times[mode].append(time.perf_counter() - t0)
                if term or trunc:
                    env.reset()
    base = statistics.median(times["training"])
    print(f"task {args.task}, action repeat {envs['training'].action_repeat}, 100x100 frames, "
          f"{args.steps} steps x {args.rounds} rounds")
    print(f"{'mode':<20} {'ms/step':>8} {'ratio':>6}")
    for mode in MODES:
        med = statistics.median(times[mode])
        print(f"{mode:<20} {1000 * med:8.2f} {med / base:6.2f}")
    for env in envs.values():
        env.close()


if __name__ == "__main__":
    main()
