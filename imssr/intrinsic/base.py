"""Where the raw intrinsic signal of o' comes from, before normalisation and beta.

IM-SSR's signal is the auxiliary task's per-sample loss of o' (:class:`~imssr.intrinsic.ssl.SSLSignal`); RND and RE3
are exploration peers that plug into the same slot, so one setting (``intrinsic.source``) swaps the signal while
normalisation, the beta schedule and everything else stay the same.
"""
from __future__ import annotations

import abc
from typing import Any, ClassVar

import torch

from imssr.batch import Batch, NextObsContext
from imssr.networks.module import ModuleWithOptimizer
from imssr.settings import AgentConfig, IntrinsicCore


class IntrinsicSignal(ModuleWithOptimizer, abc.ABC):
    """A per-sample novelty signal of the next observation."""

    name: ClassVar[str]

    def __init__(self, cfg: IntrinsicCore, obs_shape: tuple[int, ...], agent_cfg: AgentConfig, aux: Any = None):
        """The signal for an agent of ``agent_cfg`` on observations of ``obs_shape``, with the ``intrinsic`` section
        ``cfg`` (which holds the signal's own settings) and the agent's auxiliary task ``aux`` (None without one)."""
        super().__init__()

    @property
    def label(self) -> str:
        """What the signal is, for messages."""
        return f"{self.name} signal of o'"

    @abc.abstractmethod
    def forward(self, ctx: NextObsContext) -> torch.Tensor:
        """Raw signal per sample, shape ``(B,)``, without gradients."""

    def objective(self, batch: Batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """What the signal's own optimiser (:attr:`optimizer`, if it has networks to train)
        minimises on ``batch``, and its metrics."""
        raise NotImplementedError(f"the {self.name} signal trains no networks")
