"""The interface an auxiliary self-supervised task implements.

An auxiliary task owns its parameters and optimiser, reads the agent's shared
encoders, and exposes *unreduced per-sample* losses: the mean of
:meth:`per_sample_loss` is what it trains on, and :meth:`intrinsic_loss` is the
same loss for the next observation, which IM-SSR turns into a reward.  A task
may also change what the critic regresses (:meth:`critic_views`, SVEA).  The
agent knows only this interface, so a new task plugs in by registering a class
in :data:`imssr.auxiliary.AUX_TASKS`.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import ClassVar, Optional

import torch
from torch import nn

from imssr.config import AgentConfig, AuxConfig
from imssr.networks.module import ModuleWithOptimizer


@dataclass
class Batch:
    """One sampled batch on the agent's device.

    ``obs`` / ``next_obs`` are the RL views (random crops); ``raw_*`` are the
    uncropped stacks from which a task draws further views with ``generator``.
    """

    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    discount: torch.Tensor
    next_obs: torch.Tensor
    raw_obs: torch.Tensor
    raw_next_obs: torch.Tensor
    generator: torch.Generator

    def __len__(self) -> int:
        return self.obs.shape[0]


@dataclass
class NextObsContext:
    """What the critic's Bellman target already computed for ``o'``, for reuse.

    ``online_trunk`` is the online trunk's output on ``next_view`` (computed for
    the actor's next action) and ``target_latent`` the target encoder's latent of
    ``next_view`` (computed for the target Q).  Both are free for the intrinsic loss.
    """

    raw_next_obs: torch.Tensor
    next_view: torch.Tensor
    online_trunk: torch.Tensor
    target_latent: torch.Tensor
    generator: torch.Generator
    form: str = "authors"
    """``intrinsic.form``: compute the signal as the authors' code did, or as the training loss."""
    batch: Optional["Batch"] = None
    """The whole RL batch, for tasks whose loss of o' needs o or a (e.g. inverse dynamics)."""
    fused_loss: Optional[torch.Tensor] = None
    """The task's per-sample training loss from this update's fused pass (detached), or None.
    A task whose intrinsic loss is that very quantity (PAD: same (o, a, o') crops, same
    weights; equal up to float rounding) returns it instead of recomputing it."""


@dataclass
class SharedNetworks:
    """The agent's networks an auxiliary task may read or train."""

    encoder: nn.Module
    """The critic's encoder (trunk + projection), trained by the critic."""
    target_encoder: nn.Module
    """Its EMA copy (the critic target's encoder)."""
    action_dim: int


class AuxiliaryTask(ModuleWithOptimizer, abc.ABC):
    """Base class of auxiliary tasks."""

    name: ClassVar[str]
    trains: ClassVar[bool] = True
    """False for tasks without an auxiliary loss of their own (SVEA acts through the critic)."""
    fuses_with_critic: ClassVar[bool] = False
    """True if :meth:`loss_from_trunk` can compute the training loss from the critic's own
    encoder pass over the RL crop of ``o`` (``agent.update_schedule = fused``)."""
    fused_next_features: ClassVar[bool] = False
    """True if the fused loss also needs the online shared-layer features of ``batch.next_obs``
    with grad (PAD): the agent then runs its shared layers once over ``o`` and ``o'`` together
    and reuses the detached features of ``o'`` for the Bellman target's online encoding."""

    def __init__(self, shared: SharedNetworks, cfg: AuxConfig, agent_cfg: AgentConfig):
        super().__init__()
        # Plain attribute (not a registered submodule): the agent owns and saves these.
        self.__dict__["shared"] = shared
        self.cfg = cfg
        self.agent_cfg = agent_cfg

    @abc.abstractmethod
    def per_sample_loss(self, batch: Batch) -> torch.Tensor:
        """Training loss of each sample, shape ``(B,)``, with gradients."""

    @abc.abstractmethod
    def intrinsic_loss(self, ctx: NextObsContext) -> torch.Tensor:
        """The same loss for each next observation, shape ``(B,)``, without gradients."""

    def loss_from_trunk(self, batch: Batch, trunk: torch.Tensor, features: torch.Tensor,
                        next_features: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Per-sample training loss given the critic's encoder pass over ``batch.obs`` (with grad).

        ``trunk`` is the online trunk's output, ``features`` the output of its shared layers
        (``ConvTrunk.shared_features``: ``trunk`` before flattening when there is no head);
        ``next_features`` the shared-layer features of ``batch.next_obs`` (with grad) for tasks
        with ``fused_next_features``, else None.
        Only for tasks with ``fuses_with_critic``: in the fused schedule the agent adds its
        mean to the critic loss, backpropagates once, then calls :meth:`apply_gradients`.
        """
        raise NotImplementedError(f"{self.name} cannot fuse its loss with the critic's")

    def fuses(self, agent_cfg: AgentConfig) -> bool:
        """Whether the agent fuses this task's loss with the critic's: a task that can, under the
        fused schedule, trained on the RL batch (a batch of its own needs a pass of its own)."""
        return self.fuses_with_critic and agent_cfg.update_schedule == "fused" and not self.cfg.own_batch

    def fused_parameters(self) -> list:
        """What the task's optimiser steps in the fused schedule: its own parameters only,
        since the shared encoder is stepped once by the critic's optimiser on the summed gradient."""
        return list(self.parameters())

    def apply_gradients(self, step: int) -> None:
        """Optimiser step on the gradients already in place, then :meth:`after_step`."""
        self.optimizer.step()
        self.after_step(step)

    def critic_views(self, batch: Batch) -> list[tuple[torch.Tensor, float]]:
        """Observations the critic regresses to the same target, with their loss weights."""
        return [(batch.obs, 1.0)]

    def update(self, batch: Batch, step: int) -> dict[str, torch.Tensor]:
        """One optimisation step on the mean of :meth:`per_sample_loss`."""
        loss = self.per_sample_loss(batch).mean()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.apply_gradients(step)
        return {"aux_loss": loss.detach()}

    def load_data(self, device) -> None:
        """Load what the task reads from disk (SODA: its overlay images) onto ``device``.  The
        trainer calls it before the first step, so a bad image folder fails before the seed phase
        rather than at the first update; evaluation never needs it."""

    def after_step(self, step: int) -> None:
        """Hook for momentum updates of the task's own target networks."""
