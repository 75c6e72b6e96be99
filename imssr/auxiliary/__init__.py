"""Auxiliary self-supervised tasks, one module each, registered by name."""
from __future__ import annotations

from typing import TYPE_CHECKING

from imssr.auxiliary.base import AuxiliaryTask, SharedNetworks
from imssr.auxiliary.curl import CURL
from imssr.auxiliary.pad import PAD
from imssr.auxiliary.soda import SODA
from imssr.auxiliary.svea import SVEA
from imssr.errors import ImssrError

if TYPE_CHECKING:  # annotations only: the config imports the tasks for their rules
    from imssr.config import AgentConfig, AuxConfig

AUX_TASKS: dict[str, type[AuxiliaryTask]] = {t.name: t for t in (CURL, SODA, PAD, SVEA)}


def make_aux(name: str, shared: SharedNetworks, cfg: AuxConfig, agent_cfg: AgentConfig) -> AuxiliaryTask:
    if name not in AUX_TASKS:
        raise ImssrError(f"unknown auxiliary task {name!r}; valid: {', '.join(AUX_TASKS)}")
    return AUX_TASKS[name](shared, cfg, agent_cfg)


__all__ = ["AuxiliaryTask", "SharedNetworks", "CURL", "SODA", "PAD", "SVEA", "AUX_TASKS", "make_aux"]
