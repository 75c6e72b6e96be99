"""SAC heads: the tanh-Gaussian actor and the twin-Q critic."""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch
from torch import nn

from imssr.networks.encoder import Encoder, Projection
from imssr.precision import full_precision, upcast


def mlp(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(),
                         nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, out_dim))


class PolicyOutput(NamedTuple):
    """What the actor returns for a batch of trunk features."""

    mean: torch.Tensor
    """``tanh(mu)``: the deterministic action, ``(B, |A|)``."""
    action: torch.Tensor
    """A squashed sample ``tanh(mu + sigma * eps)``, or ``mean`` when not sampling, ``(B, |A|)``."""
    log_prob: Optional[torch.Tensor]
    """``log pi(action)`` with the tanh correction, ``(B, 1)``; None when not sampling."""
    log_std: torch.Tensor
    """The squashed log standard deviation, ``(B, |A|)``."""


class Actor(nn.Module):
    """Tanh-squashed Gaussian policy on the (detached) trunk features.

    ``log_std`` is squashed into ``[log_std_min, log_std_max]``; the squashing correction of the log-probability is
    SAC's (Haarnoja et al. 2018, App. C).
    """

    def __init__(self, trunk_dim: int, feature_dim: int, action_dim: int, hidden_dim: int,
                 log_std_min: float, log_std_max: float, projection_tanh: bool = False):
        super().__init__()
        self.projection = Projection(trunk_dim, feature_dim, projection_tanh)
        self.net = mlp(feature_dim, hidden_dim, 2 * action_dim)
        self.log_std_min, self.log_std_max = log_std_min, log_std_max

    def output(self, trunk_features: torch.Tensor) -> torch.Tensor:
        """The MLP's output on the projected features: ``mu`` and the unsquashed ``log_std``."""
        return self.net(self.projection(trunk_features))

    def compile(self, *args, **kwargs) -> None:
        """``torch.compile`` :meth:`output` (the layers), in place: the state dict keeps its keys.
        The tanh-Gaussian stays eager: its noise comes from a ``torch.Generator``, which Dynamo
        does not trace (the actor would be cut into three graphs around it)."""
        self.output = torch.compile(self.output, *args, **kwargs)

    def forward(self, trunk_features: torch.Tensor, generator: Optional[torch.Generator] = None,
                sample: bool = True) -> PolicyOutput:
        out = self.output(trunk_features)
        with full_precision(out):
            # The tanh-Gaussian in float32: log pi subtracts nearly equal terms and
            # log(1 - tanh^2) needs the squashed action's small distance to +-1; the noise is drawn
            # in float32 too, so both precisions draw the same noise.
            mu, log_std = upcast(out).chunk(2, dim=-1)
            log_std = torch.tanh(log_std)
            log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (log_std + 1)
            if not sample:
                mean = torch.tanh(mu)
                return PolicyOutput(mean=mean, action=mean, log_prob=None, log_std=log_std)
            noise = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
            pi = mu + noise * log_std.exp()
            log_pi = (-0.5 * noise.pow(2) - log_std).sum(-1, keepdim=True) - 0.5 * math.log(2 * math.pi) * mu.shape[-1]
            mu, pi = torch.tanh(mu), torch.tanh(pi)
            log_pi = log_pi - torch.log(torch.relu(1 - pi.pow(2)) + 1e-6).sum(-1, keepdim=True)
            return PolicyOutput(mean=mu, action=pi, log_prob=log_pi, log_std=log_std)


class QHeads(nn.Module):
    """Two independent Q networks on ``[z, a]``; ``fp32``: computed in float32 under any autocast
    (``agent.q_heads_fp32``)."""

    def __init__(self, feature_dim: int, action_dim: int, hidden_dim: int, fp32: bool = False):
        super().__init__()
        self.q1 = mlp(feature_dim + action_dim, hidden_dim, 1)
        self.q2 = mlp(feature_dim + action_dim, hidden_dim, 1)
        self.fp32 = fp32

    def forward(self, z: torch.Tensor, action: torch.Tensor):
        za = torch.cat([z, action], dim=-1)
        if self.fp32:
            with full_precision(za):
                # One state's Q varies over actions by a few percent of Q's size, about what
                # bfloat16's 8 significant bits resolve: the actor's signal would be rounding.
                za = upcast(za)
                return self.q1(za), self.q2(za)
        return self.q1(za), self.q2(za)


class Critic(nn.Module):
    """Encoder (trunk + projection) and twin Q heads."""

    def __init__(self, encoder: Encoder, action_dim: int, hidden_dim: int, q_heads_fp32: bool = False):
        super().__init__()
        self.encoder = encoder
        self.q = QHeads(encoder.out_dim, action_dim, hidden_dim, fp32=q_heads_fp32)

    def forward(self, obs: torch.Tensor, action: torch.Tensor):
        return self.q(self.encoder(obs), action)
