"""SODA: soft data augmentation (Hansen & Wang 2021), BYOL-style consistency.

The online branch (shared trunk -> projection MLP -> predictor) sees an
overlaid view, the EMA target branch (its own copies of trunk and projection,
tau = ``aux.tau``) a clean view; the loss is the squared L2 distance of the
L2-normalised outputs (paper, Appendix, Eq. sodaloss):
``||h(g(f(o_aug)))/|.| - g*(f*(o))/|.|||^2``.  Per sample it is averaged over
the latent dimensions, so the batch mean is exactly ``F.mse_loss`` as DMC-GB trains.
As in DMC-GB and the authors' code, the two branches see *independent* random
crops of o (the overlaid one cropped apart from the clean one).

SODA trains on a batch of its own (``aux.batch_size``, every ``aux.update_every``
steps), so IM-SODA's signal is computed on the RL batch's crop of o'
(``intrinsic.form``):

* ``authors`` (the authors' ``SODA.intrinsic_reward``): the online predictor on
  the *clean* crop x, the target branch on its overlay (same crop), the reverse
  of the training loss; ``l = sum_d (h/|h| - t/|t|)_d^2``, then ``log(1 + l)``.
* ``training``: the training loss's orientation (online on the overlay, target on
  the clean crop), mean over dimensions, no log.
"""
from __future__ import annotations

import copy
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from imssr.augmentations import random_crop, random_overlay
from imssr.auxiliary.base import AuxiliaryTask, SharedNetworks
from imssr.auxiliary.soda_spec import SODASettings
from imssr.batch import Batch, Encoding, NextObsContext
from imssr.data import image_pool
from imssr.networks import ema, weight_init
from imssr.precision import FP32BatchNorm1d, full_precision, upcast
from imssr.settings import AgentConfig


def bn_mlp(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    # BatchNorm always uses batch statistics: DMC-GB's SODA never leaves training
    # mode, so running statistics would never be used; keeping none makes the
    # no-grad intrinsic pass free of side effects.
    return nn.Sequential(nn.Linear(in_dim, hidden), FP32BatchNorm1d(hidden, track_running_stats=False),
                         nn.ReLU(), nn.Linear(hidden, out_dim))


class SODA(AuxiliaryTask):
    name = "soda"

    cfg: SODASettings

    def __init__(self, shared: SharedNetworks, cfg: SODASettings, agent_cfg: AgentConfig):
        super().__init__(shared, cfg, agent_cfg)
        trunk = shared.encoder.trunk
        dim = agent_cfg.feature_dim
        self.projection = bn_mlp(trunk.out_dim, dim, dim)
        self.predictor = bn_mlp(dim, dim, dim)
        self.projection.apply(weight_init)
        self.predictor.apply(weight_init)
        # The target's own copy of the trunk: SODA's EMA (tau 0.005) is separate
        # from the critic target's (encoder_tau 0.05).
        self.target_trunk = copy.deepcopy(trunk)
        self.target_projection = copy.deepcopy(self.projection)
        for p in [*self.target_trunk.parameters(), *self.target_projection.parameters()]:
            p.requires_grad_(False)
        # Loaded on first use (evaluation never overlays) and not saved: it is
        # rebuilt from its source.
        self.images: torch.Tensor | None = None

    def shared_parameters(self) -> list[nn.Parameter]:
        # The whole online trunk (the critic's projection is not on SODA's path).
        return list(self.shared.encoder.trunk.parameters())

    def load_data(self, device) -> None:
        pool = image_pool(self.agent_cfg.crop_size, self.cfg.image_dir, self.cfg.image_pool_size)
        self.images = torch.from_numpy(pool).to(device)

    def overlay(self, x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        if self.images is None or self.images.device != x.device:
            self.load_data(x.device)
        return random_overlay(x, self.images, self.cfg.overlay_alpha, generator)

    def squared_distance(self, online_view: torch.Tensor, target_view: torch.Tensor) -> torch.Tensor:
        """``(h/|h| - t/|t|)^2`` per sample and dimension, ``(B, D)``: ``h`` the online
        predictor's output on ``online_view``, ``t`` the target branch's on ``target_view``."""
        h = self.predictor(self.projection(self.shared.encoder.trunk(online_view)))
        with torch.no_grad():
            target = self.target_projection(self.target_trunk(target_view))
        with full_precision(h):  # the loss behind IM-SODA's r_int: unit vectors compared in float32
            return (F.normalize(upcast(h), dim=1) - F.normalize(upcast(target), dim=1)).pow(2)

    def per_sample_loss(self, batch: Batch, enc: Optional[Encoding] = None) -> torch.Tensor:
        # Independent crops: the clean view is the batch's crop of o, the overlaid
        # view a fresh crop of the same observation.
        augmented = self.overlay(random_crop(batch.raw_obs, self.agent_cfg.crop_size, batch.generator),
                                 batch.generator)
        return self.squared_distance(augmented, batch.obs).mean(dim=1)

    @torch.no_grad()
    def intrinsic_loss(self, ctx: NextObsContext) -> torch.Tensor:
        clean = ctx.batch.next_obs
        augmented = self.overlay(clean, ctx.generator)  # same crop
        if ctx.form == "authors":
            return torch.log1p(self.squared_distance(clean, augmented).sum(dim=1))
        return self.squared_distance(augmented, clean).mean(dim=1)

    @torch.no_grad()
    def after_step(self, step: int) -> None:
        ema([*self.shared.encoder.trunk.parameters(), *self.projection.parameters()],
            [*self.target_trunk.parameters(), *self.target_projection.parameters()], self.cfg.tau)
