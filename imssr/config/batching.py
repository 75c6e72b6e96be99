"""Which runs can train as one batch of agents (``imssr train --seeds`` / ``--runs``, a sweep's
``runs_per_process``): those whose configs agree in everything but the seed and the intrinsic
reward.  Settings only: the batch itself is :mod:`imssr.agents.batched`, the lockstep loop
:mod:`imssr.training.seeds`.
"""
from __future__ import annotations

import json
from typing import Optional, Sequence

from imssr.config.runconfig import RunConfig
from imssr.intrinsic.registry import SIGNAL_PLUGINS

SHARED_EXCEPT = {("algo",), ("train", "seed"), ("intrinsic",)}
"""What the runs of one lockstep batch may differ in: the seed, and the intrinsic reward (whose
weights-free scalars :func:`imssr.agents.batched.batch_refusal` checks), hence the algo's name
(CURL and IM-CURL)."""


def agent_refusal(agent) -> Optional[str]:
    """Why an agent with these settings (an ``AgentConfig``) cannot be a member of a batch (one
    line), or None."""
    if agent.compile != "off":
        return "seeds in one process run eagerly on CPU and as one batch on CUDA: set agent.compile=off"
    return None


def seedless(data: dict) -> str:
    """A config as a dict (:meth:`RunConfig.to_dict`, or a config file's JSON) without its seed,
    as canonical JSON text: equal for configs that differ in the seed alone, which a batch merges
    and validates once (:func:`imssr.training.entry.plan`, :func:`imssr.training.loop.checked_configs`)."""
    train = data.get("train")
    if isinstance(train, dict):
        data = {**data, "train": {k: v for k, v in train.items() if k != "seed"}}
    return json.dumps(data, sort_keys=True)


def shared_settings(cfg: RunConfig) -> dict[tuple[str, ...], object]:
    """Every setting of ``cfg`` that the runs of one lockstep batch share, by its path."""
    def flat(d: dict, prefix: tuple = ()) -> dict:
        out = {}
        for k, v in d.items():
            key = (*prefix, k)
            if key in SHARED_EXCEPT or key[:1] in SHARED_EXCEPT:
                continue
            out.update(flat(v, key) if isinstance(v, dict) else {key: v})
        return out

    return flat(cfg.to_dict())


def batch_key(cfg: RunConfig) -> tuple:
    """Runs whose keys are equal can train as one batch: the shared settings, and the intrinsic
    signal when it has weights of its own (RND, RE3: every member then needs them); ``None`` or
    the intrinsic settings but beta_0 come third (runs without the reward join any group)."""
    i = cfg.intrinsic
    weighted = i.source if i.enabled and i.source in SIGNAL_PLUGINS and SIGNAL_PLUGINS[i.source].own_networks else ""
    own = None if not i.enabled else repr(sorted((k, v) for k, v in cfg.to_dict()["intrinsic"].items()
                                                  if k not in ("beta0", "enabled")))
    return repr(sorted(shared_settings(cfg).items())), weighted, own


def lockstep_conflict(cfgs: Sequence[RunConfig]) -> Optional[str]:
    """Why ``cfgs`` cannot train in lockstep (one line naming the first setting that differs), or None."""
    first = shared_settings(cfgs[0])
    for cfg in cfgs[1:]:
        other = shared_settings(cfg)
        for key in sorted(first.keys() | other.keys()):
            if first.get(key) != other.get(key):
                return (f"runs in one process must share every setting but the seed and the intrinsic reward: "
                        f"{'.'.join(key)} is {first.get(key)!r} in one and {other.get(key)!r} in another")
    return None
