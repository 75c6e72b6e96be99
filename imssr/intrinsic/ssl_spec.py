"""IM-SSR's signal's plug-in declaration: the auxiliary task's own per-sample loss of o', and the
setting of how IM-CURL and IM-SODA compute it (no torch here; the signal is
:class:`imssr.intrinsic.ssl.SSLSignal`)."""
from __future__ import annotations

from dataclasses import dataclass

from imssr.settings import Sections, SignalPlugin

FORMS = ("authors", "training")
"""How IM-CURL's and IM-SODA's signal of o' is computed (``intrinsic.form``)."""


@dataclass
class SSLSettings:
    """IM-SSR's fields of the ``intrinsic`` section."""

    form: str = "authors"
    """How IM-CURL's and IM-SODA's signal of o' is computed (docs/algorithms.md).  ``authors``:
    as the authors' code did (IM-CURL: online z of the RL crop of o' keyed by the target encoder on the same crop;
    IM-SODA: online predictor on the clean crop vs the target on its overlay, squared distance summed over
    dimensions, then log1p).  ``training``: the task's training loss applied to o' (IM-CURL: the key on an
    independent crop, one more encoder pass; IM-SODA: the training loss's orientation, mean over dimensions).  PAD,
    SVEA, RND and RE3 have one form."""


def rules(cfg: Sections) -> list[tuple[bool, str]]:
    return [(cfg.intrinsic.form in FORMS, f"intrinsic.form must be one of {', '.join(FORMS)}")]


PLUGIN = SignalPlugin(
    name="ssl", algo_name="im-{b}", label="IM-{B}", implementation="SSLSignal", settings=SSLSettings, rules=rules,
    description="{B} with its per-sample self-supervised loss of o' as intrinsic reward",
)
