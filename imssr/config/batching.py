"""Which runs may train as one batch in one process (``imssr train --seeds`` / ``--runs``, a sweep's
``runs_per_process``), decided here alone and from their configs: those that agree in everything
but the seed and the intrinsic reward's scalars.  The batch itself is
:class:`imssr.agents.members.Members`, its lockstep loop :mod:`imssr.training.seeds`.
"""
from __future__ import annotations

import json
from typing import Optional, Sequence

from imssr.config.runconfig import RunConfig
from imssr.errors import ImssrError
from imssr.settings import STACKED_LAYOUTS

SHARED_EXCEPT = ("algo", "train.seed", "intrinsic")
"""What the runs of one batch may differ in (dotted names; a section's name: all of it): the
seed, and the intrinsic reward (whose settings but ``beta0`` and ``enabled`` its members share:
:func:`batch_refusal`), hence the algo's name (CURL and IM-CURL)."""


def agent_refusal(agent) -> Optional[str]:
    """Why an agent with these settings (an ``AgentConfig``) cannot be a member of a batch (one
    line), or None."""
    if agent.compile != "off":
        return "seeds in one process run eagerly (agent.compile is for a run alone): set agent.compile=off"
    return None


def seedless(data: dict) -> str:
    """A config as a dict (:meth:`RunConfig.to_dict`, or a config file's JSON) without its seed,
    as canonical JSON text: equal for configs that differ in the seed alone, which a batch merges
    and validates once (:func:`imssr.training.entry.plan`, :func:`imssr.training.loop.checked_configs`)."""
    train = data.get("train")
    if isinstance(train, dict):
        data = {**data, "train": {k: v for k, v in train.items() if k != "seed"}}
    return json.dumps(data, sort_keys=True)


def shared_settings(cfg: RunConfig) -> dict[str, object]:
    """Every setting of ``cfg`` that the runs of one batch share, by its dotted name."""
    return {key: value for key, value in cfg.flat().items()
            if key not in SHARED_EXCEPT and key.partition(".")[0] not in SHARED_EXCEPT}


def _intrinsic(cfg: RunConfig) -> Optional[str]:
    """The intrinsic reward's settings but ``beta0`` (None: the run has none)."""
    if not cfg.intrinsic.enabled:
        return None
    return repr(sorted((k, v) for k, v in cfg.to_dict()["intrinsic"].items() if k not in ("beta0", "enabled")))


def batch_key(cfg: RunConfig) -> tuple[str, Optional[str]]:
    """Runs may train as one batch when their shared settings (the first) are equal and those of
    them with an intrinsic reward have the same one but for beta_0 (the second; None: the run has
    none, and joins any group)."""
    return repr(sorted(shared_settings(cfg).items())), _intrinsic(cfg)


def batch_refusal(cfgs: Sequence[RunConfig]) -> Optional[str]:
    """Why ``cfgs`` cannot train as one batch (one line naming the first setting that differs), or None."""
    refusal = agent_refusal(cfgs[0].agent)
    if refusal is not None:
        return refusal
    first = shared_settings(cfgs[0])
    for cfg in cfgs[1:]:
        other = shared_settings(cfg)
        for key in sorted(first.keys() | other.keys()):
            if first.get(key) != other.get(key):
                return (f"runs in one process must share every setting but the seed and the intrinsic reward: "
                        f"{key} is {first.get(key)!r} in one and {other.get(key)!r} in another")
    if len({_intrinsic(cfg) for cfg in cfgs} - {None}) > 1:
        return "the runs of one process may differ in intrinsic.beta0 and intrinsic.enabled only"
    return None


def stacked_layout(cfg: RunConfig, new_run: bool) -> Optional[str]:
    """For ``agent.batch_layout`` ``vmap`` or ``loop`` (stacked weights, which only a saved config
    may name): a new run's one-line error naming the measurement, raised; a resumed run's line
    that it resumes as the one batch of plain agents, returned.  None for the other layouts."""
    layout = cfg.agent.batch_layout
    if layout not in STACKED_LAYOUTS:
        return None
    if new_run:
        raise ImssrError(f"agent.batch_layout={layout} (stacked weights) is not offered: measured, it was never "
                         "faster than separate processes (vmap 0.46-0.49x of them on the CPU, 0.95-1.02x of 16 on "
                         "one H100; the stacked loop slower still: docs/performance.md); use auto or streams")
    return f"imssr: agent.batch_layout={layout} (stacked weights) resumes as the one batch of plain agents"
