"""The interface an auxiliary self-supervised task implements.

An auxiliary task reads the agent's shared encoders, declares the parameters its loss trains
(its own, and those it shares with the critic's encoder), and exposes *unreduced per-sample*
losses: the mean of :meth:`~AuxiliaryTask.per_sample_loss` is what it trains on, and
:meth:`~AuxiliaryTask.intrinsic_loss` is the same loss for the next observation, which IM-SSR turns into a reward.
A task may also change what the critic regresses (:meth:`~AuxiliaryTask.critic_views`, SVEA).  The agent knows only
this interface and builds the task's optimiser from its declarations, so a new task plugs in by its two modules
(this class, and its ``*_spec.py``: settings, rules, presets) and its name in
:data:`imssr.auxiliary.AUX_PLUGINS`.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import ClassVar, Literal, Optional

import torch
from torch import nn

from imssr.batch import Batch, Encoding, NextObsContext
from imssr.networks.module import ModuleWithOptimizer
from imssr.settings import AgentConfig, AuxCore


@dataclass(kw_only=True)
class SharedNetworks:
    """The agent's networks an auxiliary task may read or train (plain references: the agent owns and saves them)."""

    encoder: nn.Module
    """The critic's encoder (trunk + projection), trained by the critic."""
    target_encoder: nn.Module
    """Its EMA copy (the critic target's encoder)."""
    action_dim: int
    """|A|, for tasks that predict actions (PAD)."""


class AuxiliaryTask(ModuleWithOptimizer, abc.ABC):
    """Base class of auxiliary tasks."""

    name: ClassVar[str]
    trains: ClassVar[bool] = True
    """False for tasks without an auxiliary loss of their own (SVEA acts through the critic)."""
    reads_critic_pass: ClassVar[Optional[Literal["obs", "obs+next_obs"]]] = None
    """What of the critic's encoder pass over the RL batch (:class:`~imssr.batch.Encoding`) the training loss can
    read instead of running a pass of its own: ``"obs"`` (CURL: the trunk output of o), ``"obs+next_obs"`` (PAD: the
    shared-layer features of o and o', with grad; the agent then encodes both in one pass), or None (SODA: views of
    its own).  The agent reads the loss from its pass under ``agent.update_schedule = fused`` when the task trains
    on the RL batch; the task itself never needs to know which schedule runs."""

    def __init__(self, shared: SharedNetworks, cfg: AuxCore, agent_cfg: AgentConfig):
        """``cfg`` is the ``aux`` section: :class:`AuxCore` and every task's settings, this
        task's among them (its ``*_spec.py``)."""
        super().__init__()
        self.shared = shared  # a dataclass, not a module: not registered, not saved twice
        self.cfg = cfg
        self.agent_cfg = agent_cfg

    @abc.abstractmethod
    def per_sample_loss(self, batch: Batch, enc: Optional[Encoding] = None) -> torch.Tensor:
        """Training loss of each sample, shape ``(B,)``, with gradients.  ``enc`` is the critic's
        encoding of ``batch`` when the loss is read from the critic's pass (see
        :attr:`reads_critic_pass`); None: the task runs its own passes."""

    @abc.abstractmethod
    def intrinsic_loss(self, ctx: NextObsContext) -> torch.Tensor:
        """The same loss for each next observation, shape ``(B,)``, without gradients."""

    def own_parameters(self) -> list[nn.Parameter]:
        """The task's own trainable parameters (its registered ones that take gradients)."""
        return [p for p in self.parameters() if p.requires_grad]

    def shared_parameters(self) -> list[nn.Parameter]:
        """The critic encoder's parameters that the task's loss trains too (none by default).
        When the loss rides on the critic's backward (fused), the critic's optimiser steps them
        once on the summed gradient and the task's optimiser only :meth:`own_parameters`."""
        return []

    def trained_parameters(self) -> list[nn.Parameter]:
        """Everything the task's optimiser steps when it trains apart from the critic, in the
        optimiser's order (that of its saved state): the shared parameters, then its own."""
        return [*self.shared_parameters(), *self.own_parameters()]

    def critic_views(self, batch: Batch) -> list[tuple[torch.Tensor, float]]:
        """Observations the critic regresses to the same target, with their loss weights."""
        return [(batch.obs, 1.0)]

    def objective(self, batch: Batch) -> torch.Tensor:
        """What the task's optimiser minimises on ``batch``: the mean of :meth:`per_sample_loss`."""
        return self.per_sample_loss(batch).mean()

    def load_data(self, device) -> None:
        """Load what the task reads from disk (SODA: its overlay images) onto ``device``.  The
        trainer calls it before the first step, so a bad image folder fails before the seed phase
        rather than at the first update; evaluation never needs it."""

    def after_step(self, step: int) -> None:
        """Hook after each step of the task's parameters: momentum updates of its own targets.
        Under ``agent.cuda_graphs`` it is recorded with the update and replayed: it must do the
        same at every step (no branch on ``step``)."""
