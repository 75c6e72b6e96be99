"""The analysis's only contact with the agent's internals: a change of the agent's update changes this file only."""
from __future__ import annotations

import numpy as np
import torch

from imssr.augmentations import center_crop
from imssr.errors import ImssrError
from imssr.seeds import INTRINSIC_SEED_OFFSET


def intrinsic_signal(agent, sample: dict[str, np.ndarray]) -> torch.Tensor:
    """The agent's raw intrinsic signal of each ``o'`` of ``sample`` (a replay batch), shape ``(B,)``:
    the per-sample SSL loss of ``o'`` (or RND's error, RE3's distance) before the in-batch normalisation and ``beta_t``
    of Algorithm 1, the left-hand side of the paper's bound.  Built as the agent builds it for its Bellman target,
    without a gradient; a contrastive loss depends on the batch it is in (the other samples are its negatives)."""
    if agent.signal is None:
        raise ImssrError("the run's algorithm has no intrinsic reward to analyse (choose an im-, +rnd or "
                         "+re3 algorithm's run)")
    with torch.no_grad():
        batch = agent.to_batch(sample)
        return agent.intrinsic_signal(batch, agent.encode(batch)).detach().flatten()


def batch_size(agent) -> int:
    """The RL batch size: the batches the agent computes its signal in."""
    return int(agent.cfg.batch_size)


def fix_draws(agent, seed: int) -> None:
    """Seed the agent's crop and extra-view generators, so that two checkpoints see the same
    crops and views of the same states and differ only by their weights."""
    agent.gen.manual_seed(seed)
    agent.intrinsic_gen.manual_seed(seed + INTRINSIC_SEED_OFFSET)


def encoder_latents(agent, stacks: np.ndarray, chunk: int = 64) -> np.ndarray:
    """``h(o)``: the critic encoder's latent (trunk + projection, the ``z`` the SSL losses compare)
    of each uint8 stack, centre-cropped as when acting, float64 ``(N, feature_dim)``.  Computed in
    fixed chunks so that equal inputs give bit-equal latents whatever scene they came from."""
    size = agent.cfg.crop_size
    out = []
    with torch.no_grad():
        for start in range(0, len(stacks), chunk):
            x = torch.as_tensor(stacks[start:start + chunk], device=agent.device)
            out.append(agent.nets.critic.encoder(center_crop(x, size)).double().cpu().numpy())
    return np.concatenate(out)
