"""Evaluation: deterministic policy (tanh of the mean), centre crop, K episodes."""
from __future__ import annotations

from typing import Optional

import numpy as np


def evaluate(agent, env, episodes: int, record: Optional[list] = None) -> list[float]:
    """Undiscounted returns of ``episodes`` episodes of ``env``.

    With ``record`` (a list), the first episode's frames (``(H, W, 3)`` uint8,
    what the agent sees) are appended to it.
    """
    returns = []
    for episode in range(episodes):
        obs, info = env.reset()
        keep = record is not None and episode == 0
        if keep:
            record.append(_hwc(info["frame"]))
        done, total = False, 0.0
        while not done:
            obs, reward, terminated, truncated, info = env.step(agent.act(obs, deterministic=True))
            if keep:
                record.append(_hwc(info["frame"]))
            total += reward
            done = terminated or truncated
        returns.append(total)
    return [float(r) for r in np.asarray(returns)]


def _hwc(frame: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.moveaxis(frame, 0, -1))


def eval_row(frame: int, step: int, mode: str, returns: list[float]) -> dict:
    """The ``eval.csv`` summary of one evaluation."""
    return {"frame": frame, "step": step, "mode": mode,
            "return_mean": float(np.mean(returns)), "return_std": float(np.std(returns)),
            "episodes": len(returns), "return_min": float(np.min(returns)),
            "return_max": float(np.max(returns))}
