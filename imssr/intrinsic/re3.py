"""RE3: random encoders for efficient exploration (Seo et al. 2021).

A randomly initialised encoder with the agent's architecture, never trained, embeds o'; the signal is
``log(1 + ||y_i - y_i^{kNN}||)``, the distance to the k-th nearest neighbour within the batch: a particle estimate of
state entropy. It has no parameters to learn, so it costs one no-grad encoder pass.
"""
from __future__ import annotations

from typing import Any

import torch
from torch import nn

from imssr.batch import NextObsContext
from imssr.intrinsic.base import IntrinsicSignal
from imssr.intrinsic.re3_spec import RE3Settings
from imssr.networks import ConvTrunk, Projection, weight_init
from imssr.settings import AgentConfig


class RE3(IntrinsicSignal):
    name = "re3"

    def __init__(self, cfg: RE3Settings, obs_shape: tuple[int, ...], agent_cfg: AgentConfig, aux: Any = None):
        super().__init__(cfg, obs_shape, agent_cfg, aux)
        trunk = ConvTrunk(obs_shape[0], agent_cfg.crop_size, agent_cfg.encoder_layers, agent_cfg.encoder_filters,
                          channels_last=agent_cfg.channels_last, final_relu=agent_cfg.final_relu)
        self.encoder = nn.Sequential(trunk, Projection(trunk.out_dim, cfg.re3_dim))
        self.encoder.apply(weight_init)
        self.encoder.requires_grad_(False)
        self.k = cfg.re3_k

    @torch.no_grad()
    def forward(self, ctx: NextObsContext) -> torch.Tensor:
        y = self.encoder(ctx.batch.next_obs)
        dist = torch.cdist(y, y)
        # The 0-th smallest distance is the sample to itself.
        kth = dist.kthvalue(self.k + 1, dim=1).values
        return torch.log1p(kth)
