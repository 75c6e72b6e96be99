"""Telling a diverged training: the first NaN or infinite training metric, by name.

The loop sums each update's metrics on the agent's device and looks at them once per episode
(one host sync), and before a checkpoint in the middle of one, so that no checkpoint holds an
agent whose update diverged.
"""
from __future__ import annotations

import math
from typing import Optional

from imssr.errors import DivergedError, NonFiniteError
from imssr.training.state import Episode

# Training metrics in the order a divergence names them: the raw intrinsic signal (its mean), which
# enters the critic's target within the same update, then the critic's loss.
DIVERGENCE_ORDER = ("r_int_raw", "critic_loss", "actor_loss", "alpha_loss", "aux_loss", "rnd_loss", "q_mean",
                    "alpha", "entropy")


def first_non_finite(values: dict, keys, names: Optional[dict[str, str]] = None) -> Optional[str]:
    """``"critic loss nan"`` for the first of ``keys`` (in :data:`DIVERGENCE_ORDER`, then the
    rest) whose value in ``values`` is NaN or infinite, named as in ``names`` or by its key;
    None when all are finite."""
    ordered = [k for k in DIVERGENCE_ORDER if k in keys] + sorted(k for k in keys if k not in DIVERGENCE_ORDER)
    for k in ordered:
        v = values.get(k)
        if isinstance(v, float) and not math.isfinite(v):
            return f"{(names or {}).get(k, k.replace('_', ' '))} {v}"
    return None


class DivergenceCheck:
    """The divergence checks of one agent's training: ``signal`` is the agent's intrinsic signal
    (None: none), which names the ``r_int_raw`` metric ("intrinsic reward (the CURL loss) nan")."""

    def __init__(self, signal=None):
        self.names = {"r_int_raw": f"intrinsic reward ({signal.label})"} if signal is not None else {}

    def in_row(self, row: dict, episode: Episode) -> Optional[str]:
        """The first non-finite metric of the finished ``episode``'s ``train.csv`` ``row``."""
        return first_non_finite(row, episode.sums, self.names)

    def in_episode(self, episode: Optional[Episode]) -> Optional[str]:
        """``"critic loss nan"`` for the open ``episode``'s first non-finite training metric so
        far (one host sync), None when all are finite or there is no episode."""
        sums = {} if episode is None else episode.sums
        return first_non_finite({k: float(v) for k, v in sums.items()}, sums, self.names)

    def raise_if_diverged(self, episode: Optional[Episode]) -> None:
        """Before a checkpoint in the middle of ``episode``: its metrics so far, which are
        otherwise checked only at its end."""
        bad = self.in_episode(episode)
        if bad:
            raise DivergedError(bad)

    def describe(self, exc: NonFiniteError, episode: Optional[Episode]) -> str:
        """What diverged: the first non-finite training metric of the open ``episode`` (one host
        sync, only now), else what ``exc`` found (the action, the intrinsic signal)."""
        return self.in_episode(episode) or str(exc)
