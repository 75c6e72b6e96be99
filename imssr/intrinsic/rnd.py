"""Random network distillation (Burda et al. 2019) on the next observation.

A fixed, randomly initialised target network embeds o'; a predictor learns to match it online (MSE on the RL batch's
next observations each update).  The per-sample prediction error is the novelty signal: it stays high for rarely
seen observations.  Unlike IM-SSR it needs networks and an optimiser of its own, which is the contrast the paper
draws.  The original normalises pixels and rewards with running statistics; here the signal goes through the same
in-batch normalisation as every other source.
"""
from __future__ import annotations

from typing import Any

import torch
from torch import nn

from imssr.batch import Batch, NextObsContext
from imssr.intrinsic.base import IntrinsicSignal
from imssr.intrinsic.rnd_spec import RNDSettings
from imssr.precision import full_precision, upcast
from imssr.settings import AgentConfig


def rnd_convs(channels: int) -> nn.Sequential:
    # RND's convolutional stack (8x8/4, 4x4/2, 3x3/1), LeakyReLU as in the original.
    return nn.Sequential(nn.Conv2d(channels, 32, 8, stride=4), nn.LeakyReLU(),
                         nn.Conv2d(32, 64, 4, stride=2), nn.LeakyReLU(),
                         nn.Conv2d(64, 64, 3, stride=1), nn.LeakyReLU(), nn.Flatten())


class RND(IntrinsicSignal):
    name = "rnd"

    def __init__(self, cfg: RNDSettings, obs_shape: tuple[int, ...], agent_cfg: AgentConfig, aux: Any = None):
        super().__init__(cfg, obs_shape, agent_cfg, aux)
        channels = obs_shape[0]
        conv_t, conv_p = rnd_convs(channels), rnd_convs(channels)
        with torch.no_grad():
            flat = conv_t(torch.zeros(1, channels, agent_cfg.crop_size, agent_cfg.crop_size)).shape[1]
        self.target = nn.Sequential(conv_t, nn.Linear(flat, cfg.rnd_dim))
        self.predictor = nn.Sequential(conv_p, nn.Linear(flat, 512), nn.ReLU(),
                                       nn.Linear(512, 512), nn.ReLU(), nn.Linear(512, cfg.rnd_dim))
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.Linear)):
                nn.init.orthogonal_(m.weight, gain=2 ** 0.5)
                nn.init.zeros_(m.bias)
        self.target.requires_grad_(False)
        self.optimizer = torch.optim.Adam(self.predictor.parameters(), lr=cfg.rnd_lr)

    def error(self, obs: torch.Tensor) -> torch.Tensor:
        x = obs.to(self.predictor[-1].weight.dtype) / 255.0
        with torch.no_grad():
            target = self.target(x)
        prediction = self.predictor(x)
        with full_precision(prediction):  # RND's r_int before normalisation, in float32
            return (upcast(prediction) - upcast(target)).pow(2).mean(dim=1)

    @torch.no_grad()
    def forward(self, ctx: NextObsContext) -> torch.Tensor:
        return self.error(ctx.batch.next_obs)

    def objective(self, batch: Batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        loss = self.error(batch.next_obs).mean()
        return loss, {"rnd_loss": loss.detach()}

