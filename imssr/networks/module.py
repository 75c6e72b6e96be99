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
