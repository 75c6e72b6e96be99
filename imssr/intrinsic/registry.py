"""The intrinsic signals by name: the registry a new signal joins (one name in
:data:`SIGNAL_PLUGINS`), and :func:`make_signal`.  Importing it imports each signal's ``*_spec``
module, not its torch code."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

from imssr.errors import ImssrError
from imssr.settings import AgentConfig, IntrinsicCore, Implementations, SignalPlugin, plugin_table

if TYPE_CHECKING:  # the signals' torch code, imported by make_signal when an agent builds one
    from imssr.intrinsic.base import IntrinsicSignal

SIGNAL_PLUGINS: dict[str, SignalPlugin] = plugin_table(__package__, "ssl", "rnd", "re3")
"""The signals ``intrinsic.source`` names, in order: each makes an algorithm of every base
(:data:`imssr.algos.SIGNALS`)."""
INTRINSIC_SIGNALS = Implementations(SIGNAL_PLUGINS)
"""Their torch classes by name, each imported on first use."""


def make_signal(cfg: IntrinsicCore, obs_shape: tuple[int, ...], agent_cfg: AgentConfig,
                aux: Any = None) -> IntrinsicSignal:
    """The signal named by ``cfg.source`` (:class:`~imssr.intrinsic.base.IntrinsicSignal`); ``aux`` is the
    agent's auxiliary task, if any."""
    if cfg.source not in SIGNAL_PLUGINS:
        raise ImssrError(f"unknown intrinsic source {cfg.source!r}; valid: {', '.join(SIGNAL_PLUGINS)}")
    return INTRINSIC_SIGNALS[cfg.source](cfg, obs_shape, agent_cfg, aux)
