"""Evaluation: deterministic policy (tanh of the mean), centre crop, K episodes."""
from __future__ import annotations

import numpy as np


def evaluate(agent, env, episodes: int) -> list[float]:
    """Undiscounted returns of ``episodes`` episodes of ``env``."""
    returns = []
    for _ in range(episodes):
        obs, _ = env.reset()
        done, total = False, 0.0
        while not done:
            obs, reward, terminated, truncated, _ = env.step(agent.act(obs, deterministic=True))
            total += reward
            done = terminated or truncated
        returns.append(total)
    return [float(r) for r in np.asarray(returns)]


def eval_row(frame: int, step: int, mode: str, returns: list[float]) -> dict:
    """The ``eval.csv`` summary of one evaluation."""
    return {"frame": frame, "step": step, "mode": mode,
            "return_mean": float(np.mean(returns)), "return_std": float(np.std(returns)),
            "episodes": len(returns), "return_min": float(np.min(returns)),
            "return_max": float(np.max(returns))}
