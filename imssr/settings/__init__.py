"""The settings layer: what a config is made of, below every plug-in and every section's user.

It imports no plug-in, no torch and nothing else of imssr: the plug-ins' ``*_spec.py`` modules
build on it, and :mod:`imssr.config` assembles it with them into a run's config.

- ``fields``: what any settings dataclass says of its fields (types, docstrings) and the bounds
  every setting shares;
- ``sections``: the sections no plug-in owns (env, agent, train), the cores of the two that the
  plug-ins extend (aux, intrinsic) and the allowed values of their settings;
- ``plugin``: what a plug-in declares (:class:`AuxPlugin`, :class:`SignalPlugin`), the preset rows
  with their sources (:class:`Setting`), and the registries' and sections' assembly.
"""
from imssr.settings.fields import (ADAM_BETA_RULE, MAX_ADDRESSABLE_BYTES, MAX_IMAGE_SIZE, MAX_INT, MAX_SEED,
                                   MAX_SHADOW_SIZE, MAX_TORCH_THREADS, MIN_CROP_SIZE, SEED_RULE, dataclass_field_docs,
                                   dataclass_field_types, type_phrase)
from imssr.settings.plugin import (AUTHORS, AUTHORS_CURL, AUTHORS_LOOP, AUTHORS_SIGNAL, DECAY, DMCGB, IMSSR,
                                   OFFICIAL_CURL, PAPER, TABLE3, TABLE5, AuxPlugin, Beta0, Implementations, Plugin,
                                   Sections, Setting, SignalPlugin, compose_section, plugin_table)
from imssr.settings.sections import (BATCH_LAYOUTS, COMPILE_MODES, NORMALIZATIONS, PRECISIONS, REPLAY_DEVICES,
                                     SCHEDULES, STACKED_LAYOUTS, TF32_MODES, UPDATE_SCHEDULES, VIDEO_FORMATS,
                                     AgentConfig, AuxCore, EnvConfig, IntrinsicCore, TrainConfig, conv_output_size,
                                     steps_for_frames)

__all__ = [
    "ADAM_BETA_RULE", "AUTHORS", "AUTHORS_CURL", "AUTHORS_LOOP", "AUTHORS_SIGNAL", "AgentConfig", "AuxCore",
    "AuxPlugin", "BATCH_LAYOUTS", "Beta0", "COMPILE_MODES", "DECAY", "DMCGB", "EnvConfig", "IMSSR", "Implementations",
    "IntrinsicCore", "MAX_ADDRESSABLE_BYTES", "MAX_IMAGE_SIZE", "MAX_INT", "MAX_SEED", "MAX_SHADOW_SIZE",
    "MAX_TORCH_THREADS", "MIN_CROP_SIZE", "NORMALIZATIONS", "OFFICIAL_CURL", "PAPER", "PRECISIONS", "Plugin",
    "REPLAY_DEVICES", "SCHEDULES", "SEED_RULE", "STACKED_LAYOUTS", "Sections", "Setting", "SignalPlugin", "TABLE3",
    "TABLE5", "TF32_MODES", "TrainConfig", "UPDATE_SCHEDULES", "VIDEO_FORMATS", "compose_section", "conv_output_size",
    "dataclass_field_docs", "dataclass_field_types", "plugin_table", "steps_for_frames", "type_phrase",
]
