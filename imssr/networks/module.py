"""A module that owns its optimiser and saves both together."""
from __future__ import annotations

from typing import Optional

import torch
from torch import nn


class ModuleWithOptimizer(nn.Module):
    """Base of plug-ins (auxiliary tasks, intrinsic signals) that may train their own parameters."""

    def __init__(self):
        super().__init__()
        self.optimizer: Optional[torch.optim.Optimizer] = None

    def full_state_dict(self) -> dict:
        state = {"module": self.state_dict()}
        if self.optimizer is not None:
            state["optimizer"] = self.optimizer.state_dict()
        return state

    def load_full_state_dict(self, state: dict) -> None:
        self.load_state_dict(state["module"])
        if self.optimizer is not None:
            self.optimizer.load_state_dict(state["optimizer"])


def ema(online, target, tau: float) -> None:
    """``target <- lerp(target, online, tau)`` for each pair of parameters (a soft target update),
    as one foreach call: one kernel launch per group on CUDA, and on CPU the same per-tensor
    ``lerp_`` as a Python loop would run, so the same numbers."""
    online, target = list(online), list(target)
    if len(online) != len(target):
        raise ValueError(f"EMA over {len(online)} online and {len(target)} target parameters")
    torch._foreach_lerp_([t.data for t in target], [p.data for p in online], tau)
    # Through ``.data`` the targets' version counters stay as they were: count the change, so
    # that copies made from the old values (bf16 casts, :class:`imssr.precision.FrozenBF16`) are
    # known to be stale.  Numbers are untouched.
    torch.autograd.graph.increment_version(target)
