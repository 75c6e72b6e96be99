"""Where the raw intrinsic signal of o' comes from, before normalisation and beta.

IM-SSR's signal is the auxiliary task's per-sample loss of o' (:class:`SSLSignal`);
RND and RE3 are exploration peers that plug into the same slot, so one setting
(``intrinsic.source``) swaps the signal while normalisation, the beta schedule
and everything else stay the same.
"""
from __future__ import annotations

import abc
from typing import TYPE_CHECKING, Callable, ClassVar

import torch

from imssr.batch import Batch, NextObsContext
from imssr.networks.module import ModuleWithOptimizer
from imssr.precision import optimizer_step

if TYPE_CHECKING:  # annotations only: the config imports the signals for their rules
    from imssr.config import RunConfig

FORMS = ("authors", "training")
"""How IM-CURL's and IM-SODA's signal of o' is computed (``intrinsic.form``)."""


class IntrinsicSignal(ModuleWithOptimizer, abc.ABC):
    """A per-sample novelty signal of the next observation."""

    name: ClassVar[str]

    @classmethod
    def config_rules(cls, cfg: RunConfig) -> list[tuple[bool, str]]:
        """The signal's rules on a config, as ``(holds, one-line error)`` pairs, asked by
        :meth:`RunConfig.validate <imssr.config.RunConfig.validate>` of every signal: a config
        carries every signal's settings, chosen or not (:meth:`chosen` says whether it is)."""
        return []

    @classmethod
    def chosen(cls, cfg: RunConfig) -> bool:
        """Whether ``cfg`` adds this signal to the reward."""
        return cfg.intrinsic.enabled and cfg.intrinsic.source == cls.name

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

    def update(self, batch: Batch, step: int) -> dict[str, torch.Tensor]:
        """Train the signal's own networks, if any, once per agent update (:meth:`objective`)."""
        if self.optimizer is None:
            return {}
        loss, metrics = self.objective(batch)
        optimizer_step(loss, self.optimizer)
        return metrics


class SSLSignal(IntrinsicSignal):
    """IM-SSR (Algorithm 1): the auxiliary task's per-sample loss of o'."""

    name = "ssl"

    @classmethod
    def config_rules(cls, cfg: RunConfig) -> list[tuple[bool, str]]:
        return [(cfg.intrinsic.form in FORMS, f"intrinsic.form must be one of {', '.join(FORMS)}")]

    def __init__(self, task_loss: Callable[[NextObsContext], torch.Tensor], task_name: str):
        super().__init__()
        # The task's bound ``intrinsic_loss``, not the task: the agent owns and saves the task.
        self.task_loss = task_loss
        self.task_name = task_name

    @property
    def label(self) -> str:
        return f"{self.task_name} per-sample loss of o'"

    @torch.no_grad()
    def forward(self, ctx: NextObsContext) -> torch.Tensor:
        return self.task_loss(ctx)
