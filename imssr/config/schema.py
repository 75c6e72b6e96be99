"""The schema of a run's config: its sections, two of them composed of the plug-ins' settings.

The ``env``, ``agent`` and ``train`` sections are :mod:`imssr.settings.sections`'s.  The ``aux``
section (:class:`AuxConfig`) is :class:`~imssr.settings.AuxCore` with the settings of every
auxiliary task of :data:`~imssr.auxiliary.registry.AUX_PLUGINS`, the ``intrinsic`` section
(:class:`IntrinsicConfig`) :class:`~imssr.settings.IntrinsicCore` with those of every signal of
:data:`~imssr.intrinsic.registry.SIGNAL_PLUGINS`; their keys are flat (``aux.overlay_alpha``).
Besides: :data:`FIELD_TYPES` (every field's type, which :mod:`imssr.config.overrides` converts to)
and :func:`field_docs` (the fields' docstrings, the CLI's help texts).
"""
from __future__ import annotations

import functools

from imssr.auxiliary.registry import AUX_PLUGINS
from imssr.intrinsic.registry import SIGNAL_PLUGINS
from imssr.settings import (AgentConfig, AuxCore, EnvConfig, IntrinsicCore, TrainConfig, compose_section,
                            dataclass_field_docs, dataclass_field_types)

AuxConfig = compose_section(
    "AuxConfig", AuxCore, AUX_PLUGINS.values(), __name__,
    "The ``aux`` section: :class:`~imssr.settings.AuxCore`, then each auxiliary task's settings.")
IntrinsicConfig = compose_section(
    "IntrinsicConfig", IntrinsicCore, SIGNAL_PLUGINS.values(), __name__,
    "The ``intrinsic`` section: :class:`~imssr.settings.IntrinsicCore`, then each signal's settings.")

SECTIONS = {"env": EnvConfig, "agent": AgentConfig, "aux": AuxConfig, "intrinsic": IntrinsicConfig,
            "train": TrainConfig}
"""Config sections and their dataclasses, in the order of :class:`~imssr.config.RunConfig`."""

FIELD_TYPES = {"algo": str, "version": int, **{f"{name}.{field}": kind for name, cls in SECTIONS.items()
                                                for field, kind in dataclass_field_types(cls).items()}}
"""``section.field`` (and the top-level ``algo``, ``version``) -> its type: bool, int, float or str."""


@functools.cache
def field_docs() -> dict[str, str]:
    """``section.field`` -> the field's docstring (:func:`~imssr.settings.dataclass_field_docs`):
    the CLI's help texts use them.  Empty when installed without sources."""
    return {f"{section}.{name}": doc for section, cls in SECTIONS.items()
            for name, doc in dataclass_field_docs(cls).items()}
