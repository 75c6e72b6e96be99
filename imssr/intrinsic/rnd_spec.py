"""RND's plug-in declaration: its settings (its networks' size and learning rate), their rules
and preset rows (no torch here; the signal is :mod:`imssr.intrinsic.rnd`)."""
from __future__ import annotations

from dataclasses import dataclass

from imssr.settings import IMSSR, Sections, Setting, SignalPlugin

MIN_CROP = 36
"""The smallest crop RND's convolutions (8x8/4, 4x4/2, 3x3/1) leave a pixel of."""


@dataclass
class RNDSettings:
    """RND's fields of the ``intrinsic`` section."""

    rnd_lr: float = 1e-4
    """Adam learning rate of RND's predictor."""
    rnd_dim: int = 128
    """Output size of RND's target and predictor networks."""


def rules(cfg: Sections) -> list[tuple[bool, str]]:
    i: RNDSettings = cfg.intrinsic
    return [(i.rnd_lr > 0 and i.rnd_dim >= 1, "intrinsic.rnd_lr must be > 0 and rnd_dim >= 1"),
            (not PLUGIN.chosen(cfg) or cfg.agent.crop_size >= MIN_CROP,
             f"intrinsic.source=rnd needs agent.crop_size >= {MIN_CROP} (RND's 8/4, 4/2, 3/1 convolutions)")]


PLUGIN = SignalPlugin(
    name="rnd", algo_name="{b}+rnd", label="{B}+RND", implementation="RND", settings=RNDSettings, rules=rules,
    description="{B} with random network distillation error of o' as intrinsic reward",
    preset=(Setting("intrinsic.rnd_lr", 1e-4, "RND (Burda et al. 2018)"),
            Setting("intrinsic.rnd_dim", 128, IMSSR, "RND's output size")),
)
