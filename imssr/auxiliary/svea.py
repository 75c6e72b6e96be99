"""SVEA: stabilised Q-value estimation under augmentation (Hansen et al. 2021).

SVEA has no auxiliary loss: the critic regresses both the clean observation and
its random-convolution view to the *clean* Bellman target,
``alpha * ||Q(f(s), a) - q||^2 + beta * ||Q(f(s_aug), a) - q||^2`` (paper,
Appendix, Eq. L_SVEA); the target never sees augmented data.

IM-SVEA (paper, Appendix "Further Extensions"): ``l_i = ||z_hat_i - z*_i||^2`` between the online critic encoder and
its target encoder on the same (unaugmented) observation, normalised in the batch.  For ``o'`` both latents are already
computed by the Bellman target, so the signal costs no encoder pass.
"""
from __future__ import annotations

from typing import Optional

import torch

from imssr.augmentations import random_conv
from imssr.auxiliary.base import AuxiliaryTask
from imssr.auxiliary.svea_spec import SVEASettings
from imssr.batch import Batch, Encoding, NextObsContext
from imssr.precision import full_precision, upcast


class SVEA(AuxiliaryTask):
    name = "svea"
    trains = False

    cfg: SVEASettings

    def critic_views(self, batch: Batch) -> list[tuple[torch.Tensor, float]]:
        return [(batch.obs, self.cfg.svea_alpha), (random_conv(batch.obs, batch.generator), self.cfg.svea_beta)]

    def per_sample_loss(self, batch: Batch, enc: Optional[Encoding] = None) -> torch.Tensor:
        """Online-vs-target latent distance of ``o`` (what IM-SVEA measures; not trained on)."""
        with torch.no_grad():
            target = self.shared.target_encoder(batch.obs)
        return (self.shared.encoder(batch.obs) - target).pow(2).sum(dim=1)

    @torch.no_grad()
    def intrinsic_loss(self, ctx: NextObsContext) -> torch.Tensor:
        z_hat = self.shared.encoder.projection(ctx.enc.next_trunk)
        with full_precision(z_hat):  # IM-SVEA's r_int before normalisation, in float32
            return (upcast(z_hat) - upcast(ctx.enc.next_latent)).pow(2).sum(dim=1)
