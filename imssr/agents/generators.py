"""An agent's random generators, their seeds and their saved state.

Every random number an update or an action uses comes from one of three ``torch.Generator``s on the agent's device
(crop offsets, overlay indices and kernels are drawn where they are used, with no copy from the host): the
augmentations, the policy noise, and the intrinsic signal's extra views.  Apart, computing ``r_int`` never shifts
the base algorithm's streams (beta = 0 is the baseline exactly), and nothing an agent does draws from torch's global
generator.
"""
from __future__ import annotations

import torch

from imssr.seeds import INTRINSIC_SEED_OFFSET, NOISE_SEED_OFFSET

KEYS = (("gen", 0), ("noise_gen", NOISE_SEED_OFFSET), ("intrinsic_gen", INTRINSIC_SEED_OFFSET))
"""Each generator's attribute and state-dict key, with the offset of its seed from the run's (:mod:`imssr.seeds`)."""


class AgentGenerators:
    """The generators of one agent seeded with ``seed`` on ``device`` (see the module's doc)."""

    def __init__(self, seed: int, device: torch.device):
        self.gen = torch.Generator(device=device).manual_seed(seed)
        """Augmentations: the RL crops and every further view of a batch."""
        self.noise_gen = torch.Generator(device=device).manual_seed(seed + NOISE_SEED_OFFSET)
        """The policy's noise."""
        self.intrinsic_gen = torch.Generator(device=device).manual_seed(seed + INTRINSIC_SEED_OFFSET)
        """The intrinsic signal's extra views."""

    def all(self) -> list[torch.Generator]:
        """The generators in :data:`KEYS`' order (what a CUDA graph registers)."""
        return [getattr(self, key) for key, _ in KEYS]

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Each generator's state under its key (keys of an agent's state dict)."""
        return {key: getattr(self, key).get_state() for key, _ in KEYS}

    def load_state_dict(self, state: dict, updates: int) -> None:
        """Set each generator from ``state``.  A state written on another device type (CPU and
        CUDA generator states differ) reseeds it instead, at its seed plus ``updates``: an exact
        resume across device types is impossible anyway."""
        seed = int(self.gen.initial_seed())
        for key, offset in KEYS:
            try:
                getattr(self, key).set_state(state[key])
            except RuntimeError:  # saved on another device type
                getattr(self, key).manual_seed(seed + offset + updates)
