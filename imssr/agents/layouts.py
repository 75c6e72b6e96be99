"""The layouts of a batch of seeds (``agent.batch_layout``): the members' weights stacked in one
:class:`~imssr.agents.batched.AgentBatch` (``vmap``, ``loop``), or each member an agent of its
own on a CUDA stream of its own (:class:`~imssr.agents.members.Members`)."""
from __future__ import annotations

from typing import Sequence

from imssr.agents.batched import AgentBatch, resolve_mode
from imssr.agents.sac import SACAgent
from imssr.agents.members import Members
from imssr.errors import ImssrError


def make_batch(members: Sequence[SACAgent], mode: str = "auto"):
    """The members as one batch in layout ``mode`` (:data:`~imssr.agents.batched.MODES`): an :class:`AgentBatch` of
    stacked weights (``vmap``, ``loop``), or agents of their own on streams
    (:class:`~imssr.agents.members.Members`)."""
    if not members:
        raise ImssrError("a batch of agents needs at least one member")
    mode = resolve_mode(mode, members[0].device)
    if mode == "streams":
        return Members(members)
    return AgentBatch(members, mode)
