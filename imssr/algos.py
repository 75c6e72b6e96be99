"""The algorithms: every base ``X`` (an auxiliary task) and its variants ``im-X`` (IM-SSR),
``X+rnd`` and ``X+re3`` (exploration peers that swap only the intrinsic signal).

A registry of names, apart from :mod:`imssr.presets` (their values), so that the config's
validation can check that ``algo`` agrees with ``aux.name`` and ``intrinsic.*`` without
importing the presets, which import the config.
"""
from __future__ import annotations

from dataclasses import dataclass

from imssr.errors import ImssrError


@dataclass(frozen=True)
class AlgoSpec:
    name: str
    aux: str
    """Name of the auxiliary task in :data:`imssr.auxiliary.AUX_TASKS`."""
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


# Each base is an auxiliary task; every base X has im-X (its own per-sample loss
# as intrinsic reward) and the exploration peers X+rnd and X+re3, which swap
# only the signal.
BASES = {
    "curl": ("CURL", "SAC + CURL: InfoNCE between two crops, momentum key encoder (Srinivas et al. 2020)"),
    "soda": ("SODA", "SAC + SODA: BYOL-style consistency of overlay vs clean view (Hansen & Wang 2021)"),
    "pad": ("PAD", "SAC + PAD's inverse-dynamics task, shared 8 of 11 conv layers (Hansen et al. 2021)"),
    "svea": ("SVEA", "SAC + SVEA: critic regressed on clean and random-conv views (Hansen et al. 2021)"),
}
SIGNALS = {
    "ssl": ("im-{b}", "IM-{B}", "{B} with its per-sample self-supervised loss of o' as intrinsic reward"),
    "rnd": ("{b}+rnd", "{B}+RND", "{B} with random network distillation error of o' as intrinsic reward"),
    "re3": ("{b}+re3", "{B}+RE3", "{B} with RE3's k-NN state entropy (fixed random encoder) as intrinsic reward"),
}


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
