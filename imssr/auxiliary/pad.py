"""PAD's inverse-dynamics task (Hansen et al. 2021): predict a_t from s_t and s_{t+1}.

``L_PAD = MSE(a_t, f(s_t, s_{t+1}))`` (paper, Appendix).  As in DMC-GB, the task
shares the first ``encoder_layers - encoder_head_layers`` convolutions with the
critic and has its own head convolutions and projection, then an MLP
``2 * feature_dim -> hidden -> hidden -> |A|``.  It trains on the RL batch every
step.  IM-PAD's intrinsic reward is the per-sample inverse-dynamics error of the
RL batch's own transitions ``(o, a, o')``: how poorly the model explains the
step that reached ``o'``.

Fused schedule (``agent.update_schedule = fused``): the agent runs the shared
layers once over ``o`` and ``o'`` together; the critic reads the features of
``o``, PAD both, and the Bellman target the detached features of ``o'``; one
backward serves both losses.  The per-sample training loss is
then IM-PAD's intrinsic loss (same crops, action and weights; equal up to float
rounding, the shared layers running on B + B inputs instead of 2B), which is
reused instead of being recomputed.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import nn

from imssr.auxiliary.base import AuxiliaryTask, Batch, NextObsContext, SharedNetworks
from imssr.config import AgentConfig, AuxConfig
from imssr.networks import Projection, mlp, weight_init
from imssr.networks.encoder import conv_stack


class PAD(AuxiliaryTask):
    name = "pad"
    fuses_with_critic = True  # the critic's shared features of o are PAD's features of o
    fused_next_features = True  # ... and those of o' serve PAD and the Bellman target alike

    def __init__(self, shared: SharedNetworks, cfg: AuxConfig, agent_cfg: AgentConfig):
        super().__init__(shared, cfg, agent_cfg)
        trunk = shared.encoder.trunk
        # Its own head layers on the shared features, laid out as the critic's head.
        self.head = conv_stack(trunk.filters, trunk.head_layers)
        if trunk.final_relu:
            self.head.append(nn.ReLU(inplace=trunk.head_layers > 0))
        self.projection = Projection(trunk.out_dim, agent_cfg.feature_dim, agent_cfg.projection_tanh)
        self.mlp = mlp(2 * agent_cfg.feature_dim, agent_cfg.hidden_dim, shared.action_dim)
        self.apply(weight_init)
        # Sequential: the shared convolutions (not the critic's head) and the task's own
        # layers.  Fused: its own layers; the shared convolutions take the summed gradient
        # through the critic's optimiser.
        params = self.fused_parameters() if self.fuses(agent_cfg) \
            else [*trunk.convs.parameters(), *self.parameters()]
        self.optimizer = torch.optim.Adam(params, lr=cfg.lr)

    def predict_from_features(self, features: torch.Tensor) -> torch.Tensor:
        """Action predicted from the shared features of ``cat([o, o'])``, ``(2B, ...)``."""
        z, z_next = self.projection(self.head(features).flatten(1)).chunk(2)
        return self.mlp(torch.cat([z, z_next], dim=1))

    @staticmethod
    def action_error(pred: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``L_PAD`` per sample: mean squared error over the action's dimensions, ``(B,)``."""
        return (pred - action).pow(2).mean(dim=1)

    def predict_action(self, obs: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        # One encoder pass over both observations.
        return self.predict_from_features(self.shared.encoder.trunk.shared_features(torch.cat([obs, next_obs])))

    def per_sample_loss(self, batch: Batch) -> torch.Tensor:
        return self.action_error(self.predict_action(batch.obs, batch.next_obs), batch.action)

    def loss_from_trunk(self, batch: Batch, trunk: torch.Tensor, features: torch.Tensor,
                        next_features: Optional[torch.Tensor] = None) -> torch.Tensor:
        if next_features is None:
            next_features = self.shared.encoder.trunk.shared_features(batch.next_obs)
        pred = self.predict_from_features(torch.cat([features, next_features]))
        return self.action_error(pred, batch.action)

    @torch.no_grad()
    def intrinsic_loss(self, ctx: NextObsContext) -> torch.Tensor:
        if ctx.fused_loss is not None:
            return ctx.fused_loss
        b = ctx.batch
        return self.action_error(self.predict_action(b.obs, ctx.next_view), b.action)
