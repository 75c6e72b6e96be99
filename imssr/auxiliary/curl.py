"""CURL: contrastive unsupervised representations (Srinivas et al. 2020).

InfoNCE with a bilinear similarity (the paper's Eq. infonce):
``logits_ij = z_i^T W k_j`` between queries ``z`` from the online encoder on one crop and keys ``k`` from the
momentum (critic-target) encoder on an independent crop; the positive of row ``i`` is column ``i``.  The per-sample
loss is the row-wise cross-entropy.  As the authors ran it (DMC-GB's CURL), it trains on the RL batch every step,
the anchor being the RL crop of o.

IM-CURL's signal of o' (``intrinsic.form``):

* ``authors`` (the authors' ``CURL.compute_intri_reward``): query = the online
  encoder on the RL crop of o' (the Bellman target already computed its trunk), key = the critic target's encoder on
  the *same* crop (the target's latent of the Bellman target, reused): no encoder pass of its own.
* ``training``: the key on an independent crop of o', as the training loss pairs
  views (one more target-encoder pass).
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from imssr.augmentations import random_crop
from imssr.auxiliary.base import AuxiliaryTask, SharedNetworks
from imssr.batch import Batch, Encoding, NextObsContext
from imssr.precision import full_precision, upcast
from imssr.settings import AgentConfig, AuxCore


class CURL(AuxiliaryTask):
    name = "curl"
    reads_critic_pass = "obs"  # the query is the critic's own encoding of the RL crop

    def __init__(self, shared: SharedNetworks, cfg: AuxCore, agent_cfg: AgentConfig):
        super().__init__(shared, cfg, agent_cfg)
        dim = shared.encoder.out_dim
        self.W = nn.Parameter(torch.rand(dim, dim))

    def shared_parameters(self) -> list[nn.Parameter]:
        # The whole online encoder: the contrastive loss trains the encoder the critic uses.
        return list(self.shared.encoder.parameters())

    def trained_parameters(self) -> list[nn.Parameter]:
        # W first: the order in which checkpoints hold CURL's optimiser state.
        return [*self.own_parameters(), *self.shared_parameters()]

    def loss_from_latents(self, z_query: torch.Tensor, z_key: torch.Tensor) -> torch.Tensor:
        labels = torch.arange(z_query.shape[0], device=z_query.device)
        with full_precision(z_query):
            # Float32 under any autocast, the log-softmax too: the positive's logit competes with B - 1
            # others that differ from it in the last bits bfloat16 would drop (its loss is IM-CURL's r_int).
            logits = upcast(z_query) @ (self.W @ upcast(z_key).T)
            # Subtracting the row max leaves the softmax unchanged and keeps exp() finite.
            logits = logits - logits.max(dim=1, keepdim=True).values
            return F.cross_entropy(logits, labels, reduction="none")

    def per_sample_loss(self, batch: Batch, enc: Optional[Encoding] = None) -> torch.Tensor:
        # The anchor: the RL crop of o (encoded by the critic's pass when ``enc`` is given).
        trunk = self.shared.encoder.trunk(batch.obs) if enc is None else enc.obs_trunk
        positive = random_crop(batch.raw_obs, self.agent_cfg.crop_size, batch.generator)
        z_query = self.shared.encoder.projection(trunk)
        with torch.no_grad():
            z_key = self.shared.target_encoder(positive)
        return self.loss_from_latents(z_query, z_key)

    @torch.no_grad()
    def intrinsic_loss(self, ctx: NextObsContext) -> torch.Tensor:
        # Query: the online encoder on the Bellman target's crop (its trunk output is reused).
        z_query = self.shared.encoder.projection(ctx.enc.next_trunk)
        if ctx.form == "authors":
            z_key = ctx.enc.next_latent  # the target encoder on that same crop
        else:
            positive = random_crop(ctx.batch.raw_next_obs, self.agent_cfg.crop_size, ctx.generator)
            z_key = self.shared.target_encoder(positive)
        return self.loss_from_latents(z_query, z_key)
