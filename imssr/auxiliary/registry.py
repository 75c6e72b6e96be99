"""The auxiliary tasks by name: the registry a new task joins (one name in :data:`AUX_PLUGINS`),
and :func:`make_aux`.  Importing it imports each task's ``*_spec`` module, not its torch code."""
from __future__ import annotations

from typing import TYPE_CHECKING

from imssr.errors import ImssrError
from imssr.settings import AgentConfig, AuxCore, AuxPlugin, Implementations, plugin_table

if TYPE_CHECKING:  # the tasks' torch code, imported by make_aux when an agent builds one
    from imssr.auxiliary.base import AuxiliaryTask, SharedNetworks

AUX_PLUGINS: dict[str, AuxPlugin] = plugin_table(__package__, "curl", "soda", "pad", "svea")
"""The tasks ``aux.name`` names, in order: each is an algorithm's base (:data:`imssr.algos.BASES`)."""
AUX_TASKS = Implementations(AUX_PLUGINS)
"""Their torch classes by name, each imported on first use."""


def make_aux(name: str, shared: SharedNetworks, cfg: AuxCore, agent_cfg: AgentConfig) -> AuxiliaryTask:
    """The task ``name`` on the agent's ``shared`` networks."""
    if name not in AUX_PLUGINS:
        raise ImssrError(f"unknown auxiliary task {name!r}; valid: {', '.join(AUX_PLUGINS)}")
    return AUX_TASKS[name](shared, cfg, agent_cfg)
