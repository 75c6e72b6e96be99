"""Environment frames per second with rendering: imssr's env against a plain dm_control loop.

    python bench/render_speed.py [--task cartpole_swingup_sparse] [--steps 250] [--rounds 3]

Baseline (same process): ``suite.load`` + ``action_repeat`` x ``env.step`` +
``physics.render(100, 100, camera_id)`` per agent step, at the suite's default
visual quality (2048-px shadow map).  Compared: ``imssr.make_env`` with the
suite's shadow map (``shadow_size=2048``) and with imssr's default
(``shadow_size=512``).  Also prints the mean absolute pixel difference between
the 2048 and 512 renders of the same states.  Timings never go in tests.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import imssr  # noqa: F401
from imssr.envs import get_task, make_env


def plain_loop(task: str, actions: np.ndarray, repeat: int, camera_id: int) -> float:
    from dm_control import suite

    spec = get_task(task)
    env = suite.load(spec.domain, spec.suite_task, task_kwargs={"random": 0})
    env.reset()
    t0 = time.perf_counter()
    frames = 0
    for a in actions:
        for _ in range(repeat):
            ts = env.step(a)
            frames += 1
        env.physics.render(100, 100, camera_id=camera_id)
        if ts.last():
            env.reset()
    return frames / (time.perf_counter() - t0)


def imssr_loop(task: str, actions: np.ndarray, shadow_size: int) -> float:
    env = make_env(task, seed=0, shadow_size=shadow_size)
    env.reset()
    t0 = time.perf_counter()
    frames = 0
    for a in actions:
        _, _, term, trunc, info = env.step(a.astype(np.float32))
        frames += info["sim_steps"]
        if term or trunc:
            env.reset()
    fps = frames / (time.perf_counter() - t0)
    env.close()
    return fps


def pixel_difference(task: str, steps: int = 50) -> tuple[float, float]:
    envs = [make_env(task, seed=0, shadow_size=s) for s in (2048, 512)]
    diffs = []
    rng = np.random.default_rng(1)
    for env in envs:
        env.reset()
    for _ in range(steps):
        a = rng.uniform(-1, 1, envs[0].action_space.shape).astype(np.float32)
        frames = [env.step(a)[4]["frame"].astype(np.int16) for env in envs]
        diffs.append(np.abs(frames[0] - frames[1]))
    for env in envs:
        env.close()
    d = np.stack(diffs)
    return float(d.mean()), float(d.max())


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--task", default="cartpole_swingup_sparse")
    p.add_argument("--steps", type=int, default=250)
    p.add_argument("--rounds", type=int, default=3)
    args = p.parse_args()
    spec = get_task(args.task)
    probe = make_env(args.task)
    shape, repeat, camera = probe.action_space.shape, probe.action_repeat, probe.camera_id
    probe.close()
    actions = np.random.default_rng(0).uniform(-1, 1, (args.steps,) + shape)
    fps = {"plain dm_control": [], "imssr shadow 2048": [], "imssr shadow 512": []}
    for _ in range(args.rounds):
        fps["plain dm_control"].append(plain_loop(spec.name, actions, repeat, camera))
        fps["imssr shadow 2048"].append(imssr_loop(spec.name, actions, 2048))
        fps["imssr shadow 512"].append(imssr_loop(spec.name, actions, 512))
    base = statistics.median(fps["plain dm_control"])
    print(f"task {spec.name}, action repeat {repeat}, 100x100, {args.steps} agent steps x {args.rounds} rounds")
    for name, values in fps.items():
        med = statistics.median(values)
        print(f"{name:<20} {med:8.0f} frames/s  ratio {med / base:5.2f}")
    mean, worst = pixel_difference(spec.name)
    print(f"pixel difference 2048 vs 512 shadow map: mean {mean:.3f}/255, max {worst:.0f}/255")


if __name__ == "__main__":
    main()
