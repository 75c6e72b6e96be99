"""PAD's inverse-dynamics task (Hansen et al. 2021): predict a_t from s_t and s_{t+1}.

``L_PAD = MSE(a_t, f(s_t, s_{t+1}))`` (paper, Appendix).  As in DMC-GB, the task shares the first
``encoder_layers - encoder_head_layers`` convolutions with the critic and has its own head convolutions and
projection, then an MLP ``2 * feature_dim -> hidden -> hidden -> |A|``.  It trains on the RL batch every step.
IM-PAD's intrinsic reward is the per-sample inverse-dynamics error of the RL batch's own transitions ``(o, a, o')``:
how poorly the model explains the step that reached ``o'``.

When the loss is read from the critic's pass (``agent.update_schedule = fused``), the agent runs the shared layers
once over ``o`` and ``o'`` together; the critic reads the features of ``o``, PAD both, and the Bellman target the
detached features of ``o'``; one backward serves both losses.  The per-sample training loss is then IM-PAD's
intrinsic loss (same crops, action and weights; equal up to float rounding, the shared layers running on B + B
inputs instead of 2B), which is reused instead of being recomputed.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import nn

from imssr.auxiliary.base import AuxiliaryTask, SharedNetworks
from imssr.batch import Batch, Encoding, NextObsContext
from imssr.networks import Projection, mlp, weight_init
from imssr.networks.encoder import conv_stack
from imssr.precision import full_precision, upcast
from imssr.settings import AgentConfig, AuxCore


class PAD(AuxiliaryTask):
    name = "pad"
    # The critic's shared features of o are PAD's features of o, and those of o' serve PAD
    # and the Bellman target alike.
    reads_critic_pass = "obs+next_obs"

    def __init__(self, shared: SharedNetworks, cfg: AuxCore, agent_cfg: AgentConfig):
        super().__init__(shared, cfg, agent_cfg)
        trunk = shared.encoder.trunk
        # Its own head layers on the shared features, laid out as the critic's head.
        self.head = conv_stack(trunk.filters, trunk.head_layers, trunk.final_relu)
        self.projection = Projection(trunk.out_dim, agent_cfg.feature_dim, agent_cfg.projection_tanh)
        self.mlp = mlp(2 * agent_cfg.feature_dim, agent_cfg.hidden_dim, shared.action_dim)
        self.apply(weight_init)

    def shared_parameters(self) -> list[nn.Parameter]:
        # The shared convolutions, not the critic's head layers.
        return list(self.shared.encoder.trunk.convs.parameters())

    def predict_from_features(self, features: torch.Tensor) -> torch.Tensor:
        """Action predicted from the shared features of ``cat([o, o'])``, ``(2B, ...)``."""
        z, z_next = self.projection(self.head(features).flatten(1)).chunk(2)
        return self.mlp(torch.cat([z, z_next], dim=1))

    @staticmethod
    def action_error(pred: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``L_PAD`` per sample: mean squared error over the action's dimensions, ``(B,)``, in
        float32 (it is IM-PAD's r_int before normalisation)."""
        with full_precision(pred):
            return (upcast(pred) - action).pow(2).mean(dim=1)

    def predict_action(self, obs: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        # One encoder pass over both observations.
        return self.predict_from_features(self.shared.encoder.trunk.shared_features(torch.cat([obs, next_obs])))

    def per_sample_loss(self, batch: Batch, enc: Optional[Encoding] = None) -> torch.Tensor:
        if enc is None:
            pred = self.predict_action(batch.obs, batch.next_obs)
        else:
            pred = self.predict_from_features(torch.cat([enc.obs_features, enc.next_features]))
        return self.action_error(pred, batch.action)

    @torch.no_grad()
    def intrinsic_loss(self, ctx: NextObsContext) -> torch.Tensor:
        if ctx.enc is not None and ctx.enc.aux_loss is not None:
            # This update's training loss, read from the critic's pass: the same transitions.
            return ctx.enc.aux_loss.detach()
        b = ctx.batch
        return self.action_error(self.predict_action(b.obs, b.next_obs), b.action)
