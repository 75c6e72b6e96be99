"""IM-SSR's signal (Algorithm 1): the auxiliary task's own per-sample loss of o'."""
from __future__ import annotations

from typing import Any, Callable

import torch

from imssr.batch import NextObsContext
from imssr.errors import ImssrError
from imssr.intrinsic.base import IntrinsicSignal
from imssr.settings import AgentConfig, IntrinsicCore


class SSLSignal(IntrinsicSignal):
    """IM-SSR (Algorithm 1): the auxiliary task's per-sample loss of o'."""

    name = "ssl"

    def __init__(self, cfg: IntrinsicCore, obs_shape: tuple[int, ...], agent_cfg: AgentConfig, aux: Any = None):
        super().__init__(cfg, obs_shape, agent_cfg, aux)
        if aux is None:
            raise ImssrError("intrinsic.source=ssl needs an auxiliary task")
        # The task's bound ``intrinsic_loss``, not the task: the agent owns and saves the task.
        self.task_loss: Callable[[NextObsContext], torch.Tensor] = aux.intrinsic_loss
        self.task_name = aux.name

    @property
    def label(self) -> str:
        return f"{self.task_name} per-sample loss of o'"

    @torch.no_grad()
    def forward(self, ctx: NextObsContext) -> torch.Tensor:
        return self.task_loss(ctx)
