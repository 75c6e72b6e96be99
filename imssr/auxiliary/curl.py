"""CURL: contrastive unsupervised representations (Srinivas et al. 2020).

InfoNCE with a bilinear similarity (the paper's Eq. infonce):
``logits_ij = z_i^T W k_j`` between queries ``z`` from the online encoder on
one crop and keys ``k`` from the momentum (critic-target) encoder on an
independent crop; the positive of row ``i`` is column ``i``.  The per-sample
loss is the row-wise cross-entropy.  As the authors ran it (DMC-GB's CURL), it
trains on the RL batch every step, the anchor being the RL crop of o.

IM-CURL's signal of o' (``intrinsic.form``):

* ``authors`` (the authors' ``CURL.compute_intri_reward``): query = the online
  encoder on the RL crop of o' (the Bellman target already computed its trunk),
  key = the critic target's encoder on the *same* crop (the target's latent of
  the Bellman target, reused): no encoder pass of its own.
* ``training``: the key on an independent crop of o', as the training loss pairs
  views (one more target-encoder pass).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from imssr.augmentations import random_crop
from imssr.auxiliary.base import AuxiliaryTask, Batch, NextObsContext, SharedNetworks
from imssr.config import AgentConfig, AuxConfig


class CURL(AuxiliaryTask):
    name = "curl"
    fuses_with_critic = True  # the query is the critic's own encoding of the RL crop

    def __init__(self, shared: SharedNetworks, cfg: AuxConfig, agent_cfg: AgentConfig):
        super().__init__(shared, cfg, agent_cfg)
        dim = shared.encoder.out_dim
        self.W = nn.Parameter(torch.rand(dim, dim))
        # Sequential schedule: one optimiser over W and the online encoder, so the
        # contrastive loss trains the encoder that the critic uses.  Fused: W only;
        # the encoder takes the summed gradient through the critic's optimiser.
        params = self.fused_parameters() if self.fuses(agent_cfg) \
            else [self.W, *shared.encoder.parameters()]
        self.optimizer = torch.optim.Adam(params, lr=cfg.lr)

    def logits(self, z_query: torch.Tensor, z_key: torch.Tensor) -> torch.Tensor:
        logits = z_query @ (self.W @ z_key.T)
        # Subtracting the row max leaves the softmax unchanged and keeps exp() finite.
        return logits - logits.max(dim=1, keepdim=True).values

    def loss_from_latents(self, z_query: torch.Tensor, z_key: torch.Tensor) -> torch.Tensor:
        labels = torch.arange(z_query.shape[0], device=z_query.device)
        return F.cross_entropy(self.logits(z_query, z_key), labels, reduction="none")

    def per_sample_loss(self, batch: Batch) -> torch.Tensor:
        return self.loss_from_trunk(batch, self.shared.encoder.trunk(batch.obs), None)

    def loss_from_trunk(self, batch: Batch, trunk: torch.Tensor, features, next_features=None) -> torch.Tensor:
        positive = random_crop(batch.raw_obs, self.agent_cfg.crop_size, batch.generator)
        z_query = self.shared.encoder.projection(trunk)
        with torch.no_grad():
            z_key = self.shared.target_encoder(positive)
        return self.loss_from_latents(z_query, z_key)

    @torch.no_grad()
    def intrinsic_loss(self, ctx: NextObsContext) -> torch.Tensor:
        # Query: the online encoder on the Bellman target's crop (its trunk output is reused).
        z_query = self.shared.encoder.projection(ctx.online_trunk)
        if ctx.form == "authors":
            z_key = ctx.target_latent  # the target encoder on that same crop
        else:
            positive = random_crop(ctx.raw_next_obs, self.agent_cfg.crop_size, ctx.generator)
            z_key = self.shared.target_encoder(positive)
        return self.loss_from_latents(z_query, z_key)
