"""What a run is made of besides its envs: the torch device and the agent its config describes
(shared by training and by the evaluation of a saved run)."""
from __future__ import annotations

import torch

from imssr._gl import pin_egl_device
from imssr.agents import SACAgent
from imssr.algos import get_algo
from imssr.config import RunConfig
from imssr.errors import ImssrError


def resolve_device(name: str) -> torch.device:
    """The torch device of ``train.device``; on CUDA, MuJoCo's EGL renders on the same GPU
    (:func:`imssr._gl.pin_egl_device`, before any env is made)."""
    device = _torch_device(name)
    if device.type == "cuda":
        pin_egl_device(device.index if device.index is not None else torch.cuda.current_device())
    return device


def _torch_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ImssrError(f"unknown device {name!r}; use cpu, cuda, cuda:N or auto") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ImssrError(f"device {name!r} requested but CUDA is not available; use --device cpu")
    if device.type not in ("cpu", "cuda"):
        raise ImssrError(f"unsupported device {name!r}; use cpu, cuda, cuda:N or auto")
    return device


def build_agent(cfg: RunConfig, obs_shape, action_dim: int, device) -> SACAgent:
    algo = get_algo(cfg.algo)
    return SACAgent(obs_shape, action_dim, cfg.agent, aux_cfg=cfg.aux if algo.aux else None,
                    intrinsic_cfg=cfg.intrinsic, device=device, seed=cfg.train.seed)


def restore_agent(agent: SACAgent, state: dict) -> SACAgent:
    """``agent`` with the networks of the checkpoint ``state`` (a trained run's, to act and be
    evaluated: its random streams stay the agent's own); a checkpoint of another config is one
    line."""
    try:
        agent.load_state_dict(state["agent"], restore_rng=False)
    except (RuntimeError, KeyError, ValueError) as exc:
        raise ImssrError(f"checkpoint does not match the run's config: {str(exc).splitlines()[0]}") from None
    return agent
