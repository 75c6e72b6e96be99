"""Many seeds of one experiment as agents of their own whose GPU work overlaps.

:class:`Members` is a batch of seeds (``imssr train --seeds``, packed sweeps): each member is a whole
:class:`~imssr.agents.sac.SACAgent`, untouched, and an agent step runs every member's own update (and action) in
turn.  What may share a batch is decided before the agents are built (:mod:`imssr.config.batching`).  On CUDA each
member issues its work on a CUDA stream of its own, all forked from the current stream and joined back into it
before the step's host work, so the GPU may run one member's kernels beside another's: a seed's update at batch 128
launches hundreds of kernels that each fill a small part of the GPU, and kernels queued on one stream run one after
another.  With ``agent.cuda_graphs`` each member's update is one recorded graph, replayed on its stream: the host
queues the members' steps in microseconds and the device runs them side by side.

A member's arithmetic is its run's alone: the same agent, the same code, the same draws from its own generators; the
streams change only when kernels run, not what they compute.  On the CPU there are no streams and the members run one
after another: bit for bit the runs alone (``tests/test_agent_batch.py``).  On CUDA, kernels whose algorithm choice
depends on timing (``cudnn.benchmark``, ``agent.tf32``'s defaults) may pick other algorithms beside other members than
alone; with deterministic cuDNN algorithms the member is its run alone (``scripts/gpu_seeds.sh`` checks it on a GPU).

Joining before host work keeps the caching allocator safe: every tensor a member's stream allocates is read on the
current stream only after that stream waited for the member's, and each member's stream waits for the current stream
before it is given new work.
"""
from __future__ import annotations

import os
from typing import Callable, Optional, Sequence, TypeVar

import numpy as np
import torch

from imssr.agents.sac import Metrics, SACAgent
from imssr.errors import ImssrError

T = TypeVar("T")


CONCURRENT_STREAMS = "32"
"""CUDA's hardware work queues per process for a batch of seeds (``CUDA_DEVICE_MAX_CONNECTIONS``;
CUDA's default is 8, its maximum 32): with fewer queues than the members' streams, the work of
independent members can wait in one queue behind each other."""


def allow_concurrent_streams() -> None:
    """Raise CUDA's work queues for a batch of seeds, unless the user set them or CUDA has
    already started in this process (CUDA reads the variable once, when it starts)."""
    if not torch.cuda.is_initialized():
        os.environ.setdefault("CUDA_DEVICE_MAX_CONNECTIONS", CONCURRENT_STREAMS)


class Members:
    """``N`` member agents of one configuration stepped in lockstep, each on a CUDA stream of its
    own (see the module's doc)."""

    def __init__(self, agents: Sequence[SACAgent]):
        if not agents:
            raise ImssrError("a batch of agents needs at least one member")
        self.members = list(agents)
        """The agents, in the batch's order."""
        self.n = len(self.members)
        """How many members."""
        self.device = self.members[0].device
        """The members' device."""
        self.streams: Optional[list[torch.cuda.Stream]] = (
            [torch.cuda.Stream(self.device) for _ in self.members] if self.device.type == "cuda" else None)
        """One stream per member on CUDA; None elsewhere (the members run in turn)."""

    def each(self, fn: Callable[[int, SACAgent], T]) -> list[T]:
        """``fn(i, member)`` for every member: on CUDA each on its stream, forked from and joined
        back into the current stream; elsewhere one after another."""
        if self.streams is None:
            return [fn(i, m) for i, m in enumerate(self.members)]
        main = torch.cuda.current_stream(self.device)
        out = []
        try:
            for i, (stream, member) in enumerate(zip(self.streams, self.members)):
                stream.wait_stream(main)
                with torch.cuda.stream(stream):
                    out.append(fn(i, member))
        finally:  # joined also when a member fails: what follows must not race its work
            for stream in self.streams:
                main.wait_stream(stream)
        return out

    def update(self, replays: Sequence, step: int) -> list[Metrics]:
        """All updates of agent step ``step`` for every member, each sampling its own replay
        buffer (``replays[i]``); one metrics dict per member, its run alone's."""
        if len(replays) != self.n:
            raise ImssrError(f"{len(replays)} replay buffers for {self.n} members")
        return self.each(lambda i, m: m.update(replays[i], step))

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool) -> torch.Tensor:
        """Each member's action ``(N, |A|)`` for its own observation stack ``obs[i]``: the observations go to the
        device in one copy and the actions come back as one tensor, so a caller reads them all with one copy."""
        x = torch.as_tensor(obs, device=self.device)

        def act(i: int, m: SACAgent) -> torch.Tensor:
            return m.graphs(("act", deterministic), lambda inputs: m.act_on(inputs, deterministic),
                            {"obs": x[i:i + 1]})

        return torch.cat(self.each(act))
