"""The records an update passes around: the sampled batch, its encoding, and the context of o'.

They live apart from the agent and its plug-ins so that auxiliary tasks (:mod:`imssr.auxiliary`) and intrinsic signals
(:mod:`imssr.intrinsic`) share them without importing each other.  Build them with keywords.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch


@dataclass(kw_only=True)
class Batch:
    """One sampled batch of ``B`` transitions ``(o, a, r, o')`` on the agent's device.

    ``obs`` / ``next_obs`` are the RL views (random crops); ``raw_*`` are the uncropped stacks
    from which a task draws further views with ``generator``.
    """

    obs: torch.Tensor
    """The RL crop of o, uint8 ``(B, C, S, S)``."""
    action: torch.Tensor
    """a, ``(B, |A|)``."""
    reward: torch.Tensor
    """The environment's reward, ``(B, 1)``."""
    discount: torch.Tensor
    """0 for a true terminal state, else 1 (the time limit is not terminal), ``(B, 1)``."""
    next_obs: torch.Tensor
    """The RL crop of o' (the Bellman target's crop), uint8 ``(B, C, S, S)``."""
    raw_obs: torch.Tensor
    """o uncropped, uint8."""
    raw_next_obs: torch.Tensor
    """o' uncropped, uint8."""
    generator: torch.Generator
    """The agent's augmentation generator: every further view of this batch draws from it."""

    def __len__(self) -> int:
        return self.obs.shape[0]


@dataclass(frozen=True, kw_only=True)
class Encoding:
    """One update's encoder passes over a :class:`Batch` (``SACAgent.encode``).

    The critic regresses one or more views of o (SVEA: the clean crop and an augmented one); they run as one pass,
    stacked in the order of ``view_weights``, the first being ``batch.obs``.  Everything about o' is computed once here
    and reused: the actor's next action and the target Q read it, and so may the intrinsic signal.
    """

    view_weights: tuple[float, ...]
    """The critic's loss weight of each view of o (``(1.0,)`` unless a task adds views)."""
    features: torch.Tensor
    """The online trunk's shared-layer features of the views of o (``ConvTrunk.shared_features``),
    ``(V * B, ...)``, with grad."""
    trunk: torch.Tensor
    """The online trunk's output on the views of o, ``(V * B, D)``, with grad."""
    next_trunk: torch.Tensor
    """The online trunk's output on ``batch.next_obs``, ``(B, D)``, without grad."""
    next_latent: torch.Tensor
    """The target encoder's latent of ``batch.next_obs``, ``(B, F)``, without grad."""
    next_features: Optional[torch.Tensor] = None
    """The shared-layer features of ``batch.next_obs`` with grad, when the task's loss reads them
    from this pass (PAD's, fused); ``next_trunk`` is then computed from them, detached.  Else None."""
    aux_loss: Optional[torch.Tensor] = None
    """The auxiliary task's per-sample training loss read from this encoding, ``(B,)`` with grad,
    when it joins the critic's backward (the fused schedule); else None."""

    @property
    def obs_trunk(self) -> torch.Tensor:
        """The online trunk's output on ``batch.obs`` (the first view), with grad."""
        return self.trunk[:len(self.trunk) // len(self.view_weights)]

    @property
    def obs_features(self) -> torch.Tensor:
        """The shared-layer features of ``batch.obs`` (the first view), with grad."""
        return self.features[:len(self.features) // len(self.view_weights)]


@dataclass(kw_only=True)
class NextObsContext:
    """What an intrinsic signal of o' is given: the batch, the update's encoding of it (reused
    for free), a generator for fresh views, and which form of the signal to compute."""

    batch: Batch
    """The whole RL batch: ``batch.next_obs`` is the crop of o' the Bellman target encoded;
    ``obs`` and ``action`` serve signals of the transition (inverse dynamics)."""
    enc: Optional[Encoding]
    """The update's :class:`Encoding` of ``batch`` (the agent always passes it; None where a
    signal reads only pixels, e.g. RND and RE3 in tests)."""
    generator: torch.Generator
    """For views the signal draws itself, apart from the batch's generator: computing a signal
    never shifts the base algorithm's random stream (beta = 0 is the base exactly)."""
    form: str = "authors"
    """``intrinsic.form``: compute the signal as the authors' code did, or as the training loss."""
