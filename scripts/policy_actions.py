"""What does a trained policy do?  Its mean action and spread over whole episodes, deterministic
(as evaluated) and sampled (as in training), from a run's checkpoint.

    .venv/bin/python scripts/policy_actions.py RUN [--checkpoint STEP] [--episodes 1] [--seed 0]

One line per episode and kind: the return, the average and range of the actor's mean action
``tanh(mu)`` (all action dimensions pooled), the share of frames where
it is saturated (``|tanh(mu)| > 0.99``), the average sampling standard deviation ``exp(log_std)``,
and a 5-bin histogram of the actions taken over [-1, 1].  A deterministic return far below the
sampled one with ``tanh(mu)`` near 0 means the behaviour lives in the noise, which evaluation
leaves out; ``tanh(mu)`` on one side of 0 in every frame is a constant push.

Made to see why some demo seeds' evaluations do not learn (docs/performance.md, "The demo").  Episodes use the run's evaluation environments (``imssr.load_run(...).make_env``).
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

import imssr
from imssr.augmentations import center_crop
from imssr.errors import ImssrError


def episode(run, deterministic: bool, seed: int) -> dict:
    agent = run.agent
    env = run.make_env(seed=seed)
    means, stds, actions, total = [], [], [], 0.0
    try:
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            with torch.no_grad():
                x = center_crop(torch.as_tensor(obs, device=agent.device).unsqueeze(0), agent.cfg.crop_size)
                with agent.autocast():
                    policy = agent.nets.actor(agent.nets.critic.encoder.trunk(x), generator=agent.noise_gen,
                                              sample=not deterministic)
            action = policy.action[0].float().cpu().numpy()
            means.append(policy.mean[0].float().cpu().numpy())
            stds.append(policy.log_std[0].float().exp().cpu().numpy())
            actions.append(action)
            obs, reward, terminated, truncated, _ = env.step(action)
            total += float(reward)
            done = terminated or truncated
    finally:
        env.close()
    means, actions = np.concatenate(means), np.concatenate(actions)
    return {"return": total, "mean": means.mean(), "min": means.min(), "max": means.max(),
            "saturated": float((np.abs(means) > 0.99).mean()), "std": float(np.mean(stds)),
            "hist": np.histogram(actions, bins=5, range=(-1, 1))[0].tolist()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a run directory")
    parser.add_argument("--checkpoint", default=None, help="agent step of a retained checkpoint, or a file "
                                                           "(default: the latest)")
    parser.add_argument("--episodes", type=int, default=1, help="episodes of each kind (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="first environment seed (default 0)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        run = imssr.load_run(args.run, checkpoint=args.checkpoint)
    except ImssrError as exc:
        print(f"policy_actions: {exc}", file=sys.stderr)
        return 2
    print(f"{run}")
    print("kind           return  tanh(mu) mean [min, max]  saturated  sigma   actions in 5 bins over [-1, 1]")
    for k in range(args.episodes):
        for deterministic in (True, False):
            r = episode(run, deterministic, args.seed + k)
            print(f"{'deterministic' if deterministic else 'sampled':<13} {r['return']:7.1f}  "
                  f"{r['mean']:+.3f} [{r['min']:+.2f}, {r['max']:+.2f}]       {r['saturated']:5.2f}   "
                  f"{r['std']:.3f}   {r['hist']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
