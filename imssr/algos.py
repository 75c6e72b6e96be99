"""The algorithms: every base ``X`` (an auxiliary task) and its variants ``im-X`` (IM-SSR),
``X+rnd`` and ``X+re3`` (exploration peers that swap only the intrinsic signal).

A registry of names made of the plug-ins' declarations, apart from :mod:`imssr.presets`, so that the config's
validation can check ``algo`` without importing the presets, which import the config.
"""
from __future__ import annotations

from dataclasses import dataclass

from imssr.auxiliary.registry import AUX_PLUGINS
from imssr.errors import ImssrError
from imssr.intrinsic.registry import SIGNAL_PLUGINS


@dataclass(frozen=True)
class AlgoSpec:
    name: str
    aux: str
    """Name of the auxiliary task in :data:`imssr.auxiliary.AUX_PLUGINS`."""
    intrinsic: str
    """Intrinsic signal: ``none`` (the base), ``ssl`` (IM-SSR), ``rnd`` or ``re3`` (peers)."""
    paper_name: str
    """Label in the paper's tables and in reports."""
    description: str

    @property
    def intrinsic_enabled(self) -> bool:
        return self.intrinsic != "none"

    @property
    def base(self) -> str:
        """The algo without intrinsic reward that this one is compared with."""
        return self.aux


BASES = {name: (p.label, p.description) for name, p in AUX_PLUGINS.items()}
"""Base name -> its paper label and description, in the registry's order."""
SIGNALS = {name: (p.algo_name, p.label, p.description) for name, p in SIGNAL_PLUGINS.items()}
"""Signal name -> its algorithm's name, paper label and description over a base (``{b}``, ``{B}``)."""


def _algos() -> dict[str, AlgoSpec]:
    algos = {}
    for b, (label, description) in BASES.items():
        algos[b] = AlgoSpec(b, b, "none", label, description)
        for signal, (name, paper, text) in SIGNALS.items():
            spec = AlgoSpec(name.format(b=b), b, signal, paper.format(B=label), text.format(B=label))
            algos[spec.name] = spec
    return algos


ALGOS = _algos()


def get_algo(name: str) -> AlgoSpec:
    if name not in ALGOS:
        raise ImssrError(f"unknown algo {name!r}; valid algos: {', '.join(ALGOS)}")
    return ALGOS[name]
