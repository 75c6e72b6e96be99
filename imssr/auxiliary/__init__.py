"""Auxiliary self-supervised tasks, one module each, registered by name."""
from imssr.auxiliary.base import AuxiliaryTask, Batch, NextObsContext, SharedNetworks
from imssr.auxiliary.curl import CURL
from imssr.errors import ImssrError

AUX_TASKS: dict[str, type[AuxiliaryTask]] = {CURL.name: CURL}


def make_aux(name: str, shared: SharedNetworks, cfg, agent_cfg) -> AuxiliaryTask:
    if name not in AUX_TASKS:
        raise ImssrError(f"unknown auxiliary task {name!r}; valid: {', '.join(AUX_TASKS)}")
    return AUX_TASKS[name](shared, cfg, agent_cfg)


__all__ = ["AuxiliaryTask", "Batch", "NextObsContext", "SharedNetworks", "CURL", "AUX_TASKS", "make_aux"]
