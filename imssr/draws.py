"""Random draws of an update, for one agent or for a batch of member agents.

Every random number an update uses (crop offsets, overlay images, random-convolution kernels,
policy noise) is drawn here, from a ``torch.Generator`` of the agent's.  A batch of member agents
(:mod:`imssr.agents.batched`, one seed each) runs the single agent's code with
:class:`MemberGenerators` in place of each generator, either under ``torch.func.vmap`` (all
members at once) or member after member (inside :func:`member`): member ``i`` then draws from its
own generator exactly what its run alone would draw (same calls, same shapes, same order); under
vmap the draws enter the vectorised computation as a batched tensor.  Code inside an update must draw
through these functions: a ``torch`` random call with a :class:`MemberGenerators` fails loudly.
"""
from __future__ import annotations

import contextlib
from typing import Iterator, Optional, Sequence

import torch
from torch._C import _functorch


class MemberGenerators:
    """One generator per member of a batch, standing in for a single agent's generator."""

    def __init__(self, generators: Sequence[torch.Generator]):
        self.generators = list(generators)

    def __len__(self) -> int:
        return len(self.generators)

    def get_state(self) -> list[torch.Tensor]:
        return [g.get_state() for g in self.generators]


_current: Optional[int] = None
"""The member whose turn it is when a batch runs its members one after another (:func:`member`)."""


@contextlib.contextmanager
def member(i: int) -> Iterator[None]:
    """Member ``i``'s turn: :class:`MemberGenerators` draw from its generator only, and
    :func:`as_member_tensor` picks its row."""
    global _current
    previous, _current = _current, i
    try:
        yield
    finally:
        _current = previous


def member_level() -> Optional[int]:
    """The level of the innermost ``vmap`` running now, None outside one."""
    return _functorch.maybe_current_level()


def is_member_batched(x: torch.Tensor) -> bool:
    """Whether ``x`` is one member's view of a batched tensor (inside a member batch's vmap)."""
    return _functorch.is_batchedtensor(x)


def as_member_tensor(values: torch.Tensor) -> torch.Tensor:
    """``values`` ``(N, ...)`` as the current member's ``(...)`` inside the members' ``vmap``
    (its leading axis the member axis), and unchanged outside one."""
    if _current is not None:
        return values[_current]
    level = member_level()
    return values if level is None else _functorch._add_batch_dim(values, 0, level)


def member_values(values: Sequence[float], dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """One scalar per member (a member's ``beta_t``) as the current member's 0-dim tensor."""
    return as_member_tensor(torch.tensor(list(values), dtype=torch.float64, device=device).to(dtype))


def randint(high: int, size: tuple[int, ...], generator, device: torch.device) -> torch.Tensor:
    """``torch.randint(0, high, size)`` from ``generator`` (per member for :class:`MemberGenerators`)."""
    if isinstance(generator, MemberGenerators):
        if _current is not None:
            return torch.randint(0, high, size, generator=generator.generators[_current], device=device)
        return as_member_tensor(torch.stack([torch.randint(0, high, size, generator=g, device=device)
                                             for g in generator.generators]))
    return torch.randint(0, high, size, generator=generator, device=device)


def randn(size: tuple[int, ...], generator, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """``torch.randn(size)`` from ``generator`` (per member for :class:`MemberGenerators`)."""
    if isinstance(generator, MemberGenerators):
        if _current is not None:
            return torch.randn(size, generator=generator.generators[_current], device=device, dtype=dtype)
        return as_member_tensor(torch.stack([torch.randn(size, generator=g, device=device, dtype=dtype)
                                             for g in generator.generators]))
    return torch.randn(size, generator=generator, device=device, dtype=dtype)
