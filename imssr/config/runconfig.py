"""RunConfig: the whole config of one run, its sections (:mod:`imssr.config.schema`) together.

Its methods join the other modules: :meth:`RunConfig.from_dict` reads a JSON object through
:mod:`imssr.config.overrides` after :func:`~imssr.config.version.check_version`, and
:meth:`RunConfig.validate` applies the rules of :mod:`imssr.config.validation`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from imssr.config.overrides import _merged
from imssr.config.schema import SECTIONS, AgentConfig, AuxConfig, EnvConfig, IntrinsicConfig, TrainConfig
from imssr.config.validation import validate_config
from imssr.config.version import CONFIG_VERSION, check_version
from imssr.errors import ImssrError
from imssr.jsonio import dumps


RESUMABLE_CHANGES = frozenset({
    "train.steps", "train.device", "train.replay_device", "train.gpu_share", "train.progress", "train.tensorboard",
    "agent.tf32", "agent.compile", "agent.fused_adam", "agent.cuda_graphs", "agent.batch_layout", "train.torch_threads",
    "train.eval_episodes", "train.eval_every_steps", "train.checkpoint_every_steps", "train.eval_modes",
    "train.save_buffer", "train.wandb", "train.wandb_project", "train.wandb_group", "train.eval_video_every",
    "train.eval_video_format", "train.env_workers"})
"""The settings a resume may change (:meth:`RunConfig.resume_conflicts`): the budget, where and how
fast the run computes, and what it evaluates, logs and keeps; every other setting shapes the
learning and is the run's own.  ``agent.precision`` and ``agent.q_heads_fp32`` are the run's own
too: reports and exports group runs by their numerics, which a switch half-way would mislabel."""


@dataclass
class RunConfig:
    algo: str = "im-curl"
    """Algorithm name (``imssr algos``)."""
    version: int = CONFIG_VERSION
    """Config format (see :data:`CONFIG_VERSION`)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    aux: AuxConfig = field(default_factory=AuxConfig)
    intrinsic: IntrinsicConfig = field(default_factory=IntrinsicConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    @property
    def total_steps(self) -> int:
        """Training budget in agent steps (T)."""
        return self.train.steps

    @property
    def total_frames(self) -> int:
        """Training budget in environment frames."""
        return self.train.steps * self.env.action_repeat

    def budget_text(self) -> str:
        """``"500,000 agent steps = 4,000,000 frames at action repeat 8"``."""
        return (f"{self.train.steps:,} agent steps = {self.total_frames:,} frames "
                f"at action repeat {self.env.action_repeat}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def resume_conflicts(self, saved: dict[str, Any]) -> list[str]:
        """The settings (dotted names, sorted) in which this config differs from ``saved``, the
        config a run was made with (a checkpoint's or ``config.json``'s object), outside
        :data:`RESUMABLE_CHANGES`: empty when this config may resume the run.  ``saved`` is read
        through this class, so settings added since the run started count as their defaults."""
        try:
            before = _flat(RunConfig.from_dict(saved).to_dict())
        except (ImssrError, TypeError):
            before = _flat(saved)
        now = self.flat()
        return sorted(k for k in before.keys() | now.keys()
                      if before.get(k) != now.get(k) and k not in RESUMABLE_CHANGES)

    def to_json(self) -> str:
        return dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "RunConfig":
        """A config from its JSON object (of this version: see :func:`check_version`); fields it
        lacks are the dataclass defaults.  Unknown fields and values of the wrong type are one-line
        errors."""
        if not isinstance(data, dict):
            raise ImssrError(f"a config must be a JSON object, got {type(data).__name__}")
        check_version(data)
        for key, value in data.items():
            if key in SECTIONS and not isinstance(value, dict):
                raise ImssrError(f"config section {key!r} must be an object, got {type(value).__name__}")
        agent = data.get("agent")
        if isinstance(agent, dict) and isinstance(agent.get("tf32"), bool):
            # A JSON boolean agent.tf32 reads as the mode of the same name.
            data = {**data, "agent": {**agent, "tf32": "true" if agent["tf32"] else "false"}}
        return _merged(cls(), data, raw={})

    def flat(self) -> dict[str, Any]:
        """Every setting under its dotted name (``agent.batch_size``), the top-level ones as they are."""
        return _flat(self.to_dict())

    def validate(self) -> "RunConfig":
        """Reject bad values with one-line errors: the general rules of :mod:`imssr.config.validation`,
        each plug-in's beside the plug-in (the ``rules`` of every auxiliary task's and intrinsic
        signal's ``*_spec.py``)."""
        validate_config(self)
        return self


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested dict's leaves under their dotted names."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out
