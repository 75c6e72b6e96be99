"""RE3's plug-in declaration: its settings (k and its random encoder's size), their rules and
preset rows (no torch here; the signal is :mod:`imssr.intrinsic.re3`)."""
from __future__ import annotations

from dataclasses import dataclass

from imssr.settings import Sections, Setting, SignalPlugin


@dataclass
class RE3Settings:
    """RE3's fields of the ``intrinsic`` section."""

    re3_k: int = 3
    """RE3: the k of the k-nearest-neighbour distance within the batch."""
    re3_dim: int = 50
    """RE3: size of the fixed random encoder's output."""


def rules(cfg: Sections) -> list[tuple[bool, str]]:
    i: RE3Settings = cfg.intrinsic
    return [(i.re3_k >= 1 and i.re3_dim >= 1, "intrinsic.re3_k and re3_dim must be >= 1"),
            # The k-th neighbour within the batch, besides the sample itself.
            (not PLUGIN.chosen(cfg) or cfg.agent.batch_size > i.re3_k, "agent.batch_size must exceed intrinsic.re3_k")]


PLUGIN = SignalPlugin(
    name="re3", algo_name="{b}+re3", label="{B}+RE3", implementation="RE3", settings=RE3Settings, rules=rules,
    description="{B} with RE3's k-NN state entropy (fixed random encoder) as intrinsic reward",
    preset=(Setting("intrinsic.re3_k", 3, "RE3 (Seo et al. 2021)"),
            Setting("intrinsic.re3_dim", 50, "RE3 (Seo et al. 2021)")),
)
