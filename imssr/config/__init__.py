"""Typed configuration.  Every field documents itself; counters say their unit.

Units: an *agent step* is one action chosen by the agent; it advances the
simulator by ``action_repeat`` *environment frames*.  Every budget, interval and
schedule here counts agent steps, as the authors' code does: the paper's
T = 500,000 agent steps (Table III, "Number of training steps"), which is
4,000,000 frames at action repeat 8.  Replay capacity counts transitions.

``CONFIG_VERSION`` 2 is the format with budgets in agent steps; imssr 0.1's configs
(version 1: budgets in frames) are refused in one line (:func:`check_version`).

The sections and the rules of a config are :mod:`imssr.settings`'s; the auxiliary tasks and the
intrinsic signals add theirs (their ``*_spec.py`` modules), and this package assembles them.
No module here imports torch.  The modules, each name re-exported here:

- ``schema``: the sections, ``aux`` and ``intrinsic`` composed of the plug-ins' settings
  (``AuxConfig``, ``IntrinsicConfig``), ``FIELD_TYPES`` and ``field_docs``;
- ``version``: ``CONFIG_VERSION`` and ``check_version``;
- ``overrides``: values merged onto a config (``apply_overrides``, ``--logger``), through OmegaConf;
- ``validation``: the rules ``RunConfig.validate`` applies, the general ones and each plug-in's
  (``check_seed``: the seed's);
- ``runconfig``: ``RunConfig``, the sections together, and the one rule of what a resume may
  change (``RESUMABLE_CHANGES``, ``RunConfig.resume_conflicts``);
- ``files``: ``read_config_file`` and ``load_config``.
"""
from imssr.config.files import load_config, read_config_file
from imssr.config.overrides import LOGGERS, apply_overrides, logger_fields, set_field
from imssr.config.runconfig import RESUMABLE_CHANGES, RunConfig
from imssr.config.schema import FIELD_TYPES, SECTIONS, AuxConfig, IntrinsicConfig, field_docs
from imssr.config.validation import check_seed
from imssr.config.version import CONFIG_VERSION, V1_KEYS, check_version
from imssr.settings import (COMPILE_MODES, MAX_ADDRESSABLE_BYTES, MAX_IMAGE_SIZE, MAX_INT, MAX_SEED, PRECISIONS,
                            REPLAY_DEVICES, SEED_RULE, TF32_MODES, UPDATE_SCHEDULES, VIDEO_FORMATS, AgentConfig,
                            EnvConfig, TrainConfig, dataclass_field_docs, dataclass_field_types, steps_for_frames,
                            type_phrase)

__all__ = [
    "AgentConfig", "AuxConfig", "COMPILE_MODES", "CONFIG_VERSION", "EnvConfig", "FIELD_TYPES", "IntrinsicConfig",
    "LOGGERS", "MAX_ADDRESSABLE_BYTES", "MAX_IMAGE_SIZE", "MAX_INT", "MAX_SEED", "PRECISIONS", "REPLAY_DEVICES",
    "RESUMABLE_CHANGES", "RunConfig", "SECTIONS", "SEED_RULE", "TF32_MODES", "TrainConfig", "UPDATE_SCHEDULES",
    "V1_KEYS", "VIDEO_FORMATS", "apply_overrides", "check_seed", "check_version", "dataclass_field_docs",
    "dataclass_field_types", "field_docs", "load_config", "logger_fields", "read_config_file", "set_field",
    "steps_for_frames", "type_phrase",
]
