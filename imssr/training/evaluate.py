"""Evaluation: deterministic policy (tanh of the mean), centre crop, K episodes."""
from __future__ import annotations

from typing import Optional

import numpy as np

from imssr.errors import DivergedError


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
            action = agent.act(obs, deterministic=True)
            if not np.isfinite(action).all():
                # The simulator would end in a PhysicsError traceback; the trainer adds the step.
                raise DivergedError(f"evaluation action {non_finite_text(action)}")
            obs, reward, terminated, truncated, info = env.step(action)
            if keep:
                record.append(_hwc(info["frame"]))
            total += reward
            done = terminated or truncated
        returns.append(total)
    return [float(r) for r in np.asarray(returns)]


def non_finite_text(values) -> str:
    """The first non-finite value of ``values`` as text: ``nan``, ``inf`` or ``-inf``."""
    values = np.asarray(values, dtype=np.float64).ravel()
    bad = values[~np.isfinite(values)]
    return str(float(bad[0])) if bad.size else "finite"


def _hwc(frame: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.moveaxis(frame, 0, -1))


def eval_row(frame: int, step: int, mode: str, returns: list[float]) -> dict:
    """The ``eval.csv`` summary of one evaluation."""
    return {"frame": frame, "step": step, "mode": mode,
            "return_mean": float(np.mean(returns)), "return_std": float(np.std(returns)),
            "episodes": len(returns), "return_min": float(np.min(returns)),
            "return_max": float(np.max(returns))}
