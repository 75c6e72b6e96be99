"""IM-SSR's intrinsic reward: in-batch normalisation and the beta schedule.

The paper's Eq. (1): ``R_t = R^ext_t + beta_t * R^int_t`` where ``R^int`` is the auxiliary task's per-sample loss of
the next observation (Algorithm 1; RND-style "predicted observation error of the next state", Appendix), normalised
within the RL batch because "it is the relative value inside one batch that matters".
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from imssr.errors import ImssrError
from imssr.precision import full_precision, upcast
from imssr.settings import NORMALIZATIONS, SCHEDULES, IntrinsicCore


def normalize(losses: torch.Tensor, method: str = "zscore", eps: float = 0.0, unbiased: bool = True,
              rtol: float = 1e-5) -> torch.Tensor:
    """Normalise per-sample losses ``(B,)`` within the batch (Algorithm 1's ``Normalize``).

    * ``zscore``: ``(l - mean) / (std + eps)``, the unbiased std unless ``unbiased`` is false;
      zero-mean, unit spread: the bonus reorders states without shifting the reward level.
      The authors' IM-CURL: eps 0; their IM-SODA: eps 1e-5.
    * ``minmax``: ``(l - min) / (max - min + eps)`` in [0, 1]; a non-negative bonus.
    * ``mean``: ``l / (mean + eps)``; keeps ratios, mean 1.
    * ``none``: the raw loss.

    A batch whose spread (zscore: std; minmax: max - min) is at most ``rtol * max(|mean|, 1e-12)`` gives zeros: the
    losses are equal up to float rounding, and dividing their rounding error by a tiny spread would hand out a large
    constant bonus (all 0.3: +0.75 per sample with eps 1e-8). Non-finite losses give non-finite values; the training
    loop stops the run on them (:class:`IntrinsicReward`).
    """
    if method == "none":
        return losses
    if method == "mean":
        return losses / (losses.mean() + eps)
    if method not in ("zscore", "minmax"):
        raise ImssrError(f"unknown normalization {method!r}; valid: {', '.join(NORMALIZATIONS)}")
    mean = losses.mean()
    if method == "zscore":
        spread = losses.std(unbiased=unbiased) if losses.numel() > 1 else torch.zeros_like(mean)
        centred = losses - mean
    else:
        lo = losses.min()
        spread, centred = losses.max() - lo, losses - lo
    # One comparison on the device; no host sync.
    flat = spread <= rtol * mean.abs().clamp_min(1e-12)
    return torch.where(flat, torch.zeros_like(losses), centred / (spread + eps))


@dataclass
class BetaSchedule:
    """``beta_t`` as a function of the agent step.

    ``constant``: ``beta_0``.  ``step``: ``beta_0 * decay ** floor(step / every)``;
    the paper's default multiplies by 0.8 every 100k steps.
    """

    beta0: float
    kind: str = "step"
    decay: float = 0.8
    every_steps: int = 100_000

    def __post_init__(self):
        if self.kind not in SCHEDULES:
            raise ImssrError(f"unknown beta schedule {self.kind!r}; valid: {', '.join(SCHEDULES)}")

    def __call__(self, step: int) -> float:
        if self.kind == "constant":
            return self.beta0
        return self.beta0 * self.decay ** math.floor(step / self.every_steps)

    @classmethod
    def of(cls, cfg: IntrinsicCore) -> "BetaSchedule":
        """The schedule the ``intrinsic`` section ``cfg`` describes."""
        return cls(cfg.beta0, cfg.schedule, cfg.decay, cfg.decay_every_steps)


class IntrinsicReward:
    """Turns per-sample losses into ``beta_t * normalize(l)`` and keeps statistics."""

    def __init__(self, cfg: IntrinsicCore):
        self.cfg = cfg

    def __call__(self, losses: torch.Tensor,
                 beta: "float | torch.Tensor") -> tuple[torch.Tensor, dict[str, torch.Tensor | float]]:
        """Return the bonus to add to the reward, shape ``(B, 1)``, and log values (tensors on
        the losses' device: nothing here waits for the device).  ``beta``: ``beta_t``
        (:class:`BetaSchedule`), a float or, under CUDA graphs, a float64 0-dim tensor.

        A non-finite loss turns every reward of the batch into NaN through the batch statistics, and the critic with
        it.  It also makes ``r_int_raw`` (the losses' mean) non-finite, which the training loop checks with the other
        metrics and stops the run on, naming the agent step and the signal.
        """
        with full_precision(losses):
            # Float32 under any autocast: the normalisation divides small differences of
            # per-sample losses by their spread.
            losses = upcast(losses.detach().flatten())
            c = self.cfg
            r_int = normalize(losses, c.normalization, c.norm_eps, c.unbiased_std, c.norm_rtol)
            # A CUDA graph reads beta as a float64 tensor: it multiplies as the Python float does,
            # rounded to the losses' dtype.
            scale = beta.to(r_int.dtype) if isinstance(beta, torch.Tensor) else beta
            # r_int is normalised (zscore: mean 0, std 1 by construction), so the raw
            # loss's spread and the bonus actually added are logged too.
            stats = {"r_int_mean": r_int.mean(), "r_int_std": r_int.std(unbiased=False),
                     "r_int_raw": losses.mean(), "r_int_raw_std": losses.std(unbiased=False),
                     "bonus_std": scale * r_int.std(unbiased=False), "beta": beta}
            return (scale * r_int).unsqueeze(-1), stats
