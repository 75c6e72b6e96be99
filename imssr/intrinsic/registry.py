"""The intrinsic signals by name: the registry a new signal joins (one line), and :func:`make_signal`."""
from __future__ import annotations

from typing import TYPE_CHECKING

from imssr.errors import ImssrError
from imssr.intrinsic.base import IntrinsicSignal, SSLSignal
from imssr.intrinsic.re3 import RE3
from imssr.intrinsic.rnd import RND

if TYPE_CHECKING:  # annotations only: the config imports the signals for their rules
    from imssr.config import AgentConfig, IntrinsicConfig

INTRINSIC_SIGNALS: dict[str, type[IntrinsicSignal]] = {s.name: s for s in (SSLSignal, RND, RE3)}
"""The signals ``intrinsic.source`` names, in the order of :data:`imssr.algos.SIGNALS`."""


def make_signal(cfg: IntrinsicConfig, obs_shape: tuple[int, ...], agent_cfg: AgentConfig,
                aux=None) -> IntrinsicSignal:
    """The signal named by ``cfg.source``; ``ssl`` needs the auxiliary task (anything with a
    ``name`` and an ``intrinsic_loss(ctx)``)."""
    if cfg.source == "ssl":
        if aux is None:
            raise ImssrError("intrinsic.source=ssl needs an auxiliary task")
        return SSLSignal(aux.intrinsic_loss, aux.name)
    if cfg.source == "rnd":
        return RND(obs_shape[0], agent_cfg.crop_size, cfg)
    if cfg.source == "re3":
        return RE3(obs_shape[0], agent_cfg, cfg)
    raise ImssrError(f"unknown intrinsic source {cfg.source!r}; valid: {', '.join(INTRINSIC_SIGNALS)}")
