"""SVEA's plug-in declaration: its settings (the weights of its two critic views), their rule,
its preset rows and those of IM-SVEA (no torch here; the task is :mod:`imssr.auxiliary.svea`)."""
from __future__ import annotations

from dataclasses import dataclass

from imssr.settings import DMCGB, TABLE3, AuxPlugin, Beta0, Sections, Setting


@dataclass
class SVEASettings:
    """SVEA's fields of the ``aux`` section."""

    svea_alpha: float = 0.5
    """SVEA: weight of the critic loss on the clean observation."""
    svea_beta: float = 0.5
    """SVEA: weight of the critic loss on the random-conv augmented observation."""


def rules(cfg: Sections) -> list[tuple[bool, str]]:
    x: SVEASettings = cfg.aux
    return [(x.svea_alpha >= 0.0 and x.svea_beta >= 0.0 and x.svea_alpha + x.svea_beta > 0,
             "aux.svea_alpha and aux.svea_beta must be >= 0 and not both 0")]


PLUGIN = AuxPlugin(
    name="svea", label="SVEA", implementation="SVEA", settings=SVEASettings, rules=rules,
    description="SAC + SVEA: critic regressed on clean and random-conv views (Hansen et al. 2021)",
    preset=(
        Setting("agent.encoder_layers", 11, TABLE3),
        Setting("agent.encoder_head_layers", 0, DMCGB),
        Setting("aux.svea_alpha", 0.5, DMCGB),
        Setting("aux.svea_beta", 0.5, DMCGB),
        Setting("train.replay_capacity", 500_000, TABLE3),
    ),
    # The paper reports beta_0 = 0.05 for IM-SVEA and no other value; the authors' code has no
    # IM-SVEA, so its normalisation follows IM-CURL's (the default).
    beta0=Beta0(every_task=0.05, every_task_source="paper (beta_0 = 0.05 for IM-PAD / IM-SVEA)"),
)
