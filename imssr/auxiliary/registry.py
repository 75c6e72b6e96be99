"""The auxiliary tasks by name: the registry a new task joins (one line), and :func:`make_aux`."""
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
"""The tasks ``aux.name`` names (the bases of :data:`imssr.algos.BASES`, in that order)."""


def make_aux(name: str, shared: SharedNetworks, cfg: AuxConfig, agent_cfg: AgentConfig) -> AuxiliaryTask:
    """The task ``name`` on the agent's ``shared`` networks."""
    if name not in AUX_TASKS:
        raise ImssrError(f"unknown auxiliary task {name!r}; valid: {', '.join(AUX_TASKS)}")
    return AUX_TASKS[name](shared, cfg, agent_cfg)
