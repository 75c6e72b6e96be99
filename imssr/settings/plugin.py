"""What a plug-in declares beside its code: its settings, their rules and its preset rows.

An auxiliary task (an algorithm's base) or an intrinsic signal is two modules in its package:
``<name>.py``, the torch module that computes it, and ``<name>_spec.py``, which imports no torch
and holds its :class:`AuxPlugin` or :class:`SignalPlugin` as ``PLUGIN``, with the settings
dataclass and the rules it names.  A registry is one line,
:func:`plugin_table` over the names; the config composes each plug-in's settings dataclass into
its section (:func:`compose_section`), the presets read its rows, and the agent imports its
implementation only when it builds one (:meth:`Plugin.implementation_class`).
"""
from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, Mapping, Optional, Protocol

from imssr.settings.sections import AgentConfig, EnvConfig, TrainConfig

# -- where a preset value comes from --------------------------------------------------------
# The authors' code is duchenzhuang/dmc-disentangle (a fork of DMC-GB that produced the paper's
# numbers); Table III wins where it speaks.
TABLE3 = "Table III"
TABLE5 = "Table V"
PAPER = "paper, Appendix (Implementation Details)"
AUTHORS = "authors' code (arguments.py default)"
AUTHORS_LOOP = "authors' code (train.py)"
AUTHORS_CURL = "authors' scripts/curl/*.sh (DMC-GB CURL)"
AUTHORS_SIGNAL = "authors' code (intrinsic reward)"
DMCGB = "DMC-GB"
OFFICIAL_CURL = "official CURL"
IMSSR = "imssr"
DECAY = "x0.8 every 100k agent steps"
"""The note of the paper's beta schedule outside its constant-beta task."""


@dataclass(frozen=True)
class Setting:
    """One preset value and where it comes from."""

    field: str
    """Dotted config field, ``section.name``."""
    value: object
    source: str
    note: str = ""
    """Why, where the value deviates from the authors' code or needs a word."""

    @property
    def deviation(self) -> bool:
        return bool(self.note) and self.note.startswith("deviation")


class Sections(Protocol):
    """A run config as the rules see it (:class:`imssr.config.RunConfig` is one): its sections."""

    algo: str
    version: int
    env: EnvConfig
    agent: AgentConfig
    aux: Any
    """An :class:`AuxCore` that is also every auxiliary task's settings dataclass."""
    intrinsic: Any
    """An :class:`IntrinsicCore` that is also every signal's settings dataclass."""
    train: TrainConfig


Rules = Callable[[Sections], "list[tuple[bool, str]]"]
"""A plug-in's rules on a config: ``(holds, one-line error)`` pairs.  A config carries every
plug-in's settings, chosen or not, so a rule on another section tests whether the plug-in is
chosen (``cfg.aux.name``, ``cfg.intrinsic.source``)."""


@dataclass(frozen=True, kw_only=True)
class Plugin:
    """What every plug-in declares."""

    name: str
    """Its name in the config (``aux.name``, ``intrinsic.source``)."""
    implementation: str
    """The name of its torch class in ``<package>.<name>``, the module beside its ``*_spec.py``,
    imported when an agent builds it."""
    settings: Optional[type] = None
    """A dataclass of its own fields, every one with a default and a docstring, composed flat
    into its config section (``aux.overlay_alpha``); None: it has none."""
    rules: Rules = lambda cfg: []
    """Its rules on a config (:data:`Rules`); none by default."""
    preset: tuple[Setting, ...] = ()
    """The preset values it sets, with their sources, in the order ``imssr config --explain``
    shows them."""
    module: str = ""
    """Its torch module, ``<package>.<name>`` (set by :func:`plugin_table`)."""

    run_fields: tuple[str, ...] = ()
    """Those of its settings that say where its data comes from, not what it learns (SODA's
    image folder): the presets show them as run settings, with the schema's defaults."""

    def implementation_class(self) -> type:
        """The torch class that computes it (imports torch)."""
        if not self.module:
            raise TypeError(f"the plug-in {self.name!r} is not registered: its registry's plugin_table "
                            "sets the module of its implementation")
        return getattr(importlib.import_module(self.module), self.implementation)


@dataclass(frozen=True)
class Beta0:
    """beta_0 of a base's intrinsic reward, per task, with its source."""

    by_task: Mapping[str, float] = field(default_factory=dict)
    """Table V's values."""
    every_task: Optional[float] = None
    """The paper's one value for the tasks outside :attr:`by_task` (None: imssr's default)."""
    every_task_source: str = ""
    """Where :attr:`every_task` comes from."""
    notes: Mapping[str, str] = field(default_factory=dict)
    """Task -> why the value differs from the authors' scripts."""


@dataclass(frozen=True, kw_only=True)
class AuxPlugin(Plugin):
    """An auxiliary self-supervised task: an algorithm's base ``X`` (and ``im-X``, ``X+rnd``, ...)."""

    label: str
    """Its name in the paper's tables and in reports (``CURL``)."""
    description: str
    """One line for ``imssr algos``."""
    beta0: Beta0 = Beta0()
    """beta_0 of its IM- variant per task."""
    schedule: Setting = Setting("intrinsic.schedule", "step", PAPER, DECAY)
    """Its IM- variant's beta schedule, on a task where the paper decays beta."""
    constant_beta_schedule: Setting = Setting("intrinsic.schedule", "constant", PAPER,
                                              "beta fixed on cartpole_swingup_sparse")
    """Its IM- variant's beta schedule on the tasks where the paper keeps beta fixed."""
    norm_eps: Setting = Setting("intrinsic.norm_eps", 0.0, IMSSR, "no code of the authors: as IM-CURL")
    """The normalisation's epsilon of its IM- variant, as the authors' code computes it."""


@dataclass(frozen=True, kw_only=True)
class SignalPlugin(Plugin):
    """An intrinsic signal of o' (``intrinsic.source``): IM-SSR's or an exploration peer's."""

    algo_name: str
    """The name of its algorithm over base ``{b}`` (``im-{b}``, ``{b}+rnd``)."""
    label: str
    """The same in the paper's style, over ``{B}`` (``IM-{B}``)."""
    description: str
    """One line for ``imssr algos``, over ``{B}``."""

    def chosen(self, cfg: Sections) -> bool:
        """Whether ``cfg`` adds this signal to the reward (its rules on other sections ask)."""
        return cfg.intrinsic.enabled and cfg.intrinsic.source == self.name


def plugin_table(package: str, *names: str) -> dict[str, Any]:
    """The plug-ins ``names`` of ``package``, in that order: each one's ``<package>.<name>_spec``
    module's ``PLUGIN``, its torch code in ``<package>.<name>`` (not imported here)."""
    table = {}
    for name in names:
        plugin = importlib.import_module(f"{package}.{name}_spec").PLUGIN
        if plugin.name != name:
            raise TypeError(f"{package}.{name}_spec declares the plug-in {plugin.name!r}, not {name!r}")
        table[name] = dataclasses.replace(plugin, module=f"{package}.{name}")
    return table


class Implementations(Mapping[str, type]):
    """A registry's torch classes by name, each imported on first use
    (:meth:`Plugin.implementation_class`)."""

    def __init__(self, plugins: Mapping[str, Plugin]):
        self._plugins = plugins

    def __getitem__(self, name: str) -> type:
        return self._plugins[name].implementation_class()

    def __contains__(self, name: object) -> bool:  # without importing the class
        return name in self._plugins

    def __iter__(self) -> Iterator[str]:
        return iter(self._plugins)

    def __len__(self) -> int:
        return len(self._plugins)


def compose_section(name: str, core: type, plugins: Iterable[Plugin], module: str, doc: str) -> type:
    """The dataclass ``name``: the fields of ``core``, then each plug-in's settings in the order
    of ``plugins``, flat; an instance is an instance of each of them.  Two plug-ins may not
    declare the same field."""
    owners: dict[str, str] = {f.name: core.__name__ for f in dataclasses.fields(core)}
    bases = []
    for plugin in plugins:
        if plugin.settings is None:
            continue
        for f in dataclasses.fields(plugin.settings):
            if f.name in owners:
                raise TypeError(f"{name}.{f.name} is declared by both {owners[f.name]} and {plugin.name}")
            owners[f.name] = plugin.name
        bases.append(plugin.settings)
    # A dataclass's fields follow its reversed MRO: the core's first, then the plug-ins' in order.
    cls = dataclasses.make_dataclass(name, [], bases=(*reversed(bases), core), namespace={"__doc__": doc})
    cls.__module__ = module  # pickled and printed under the name its module exports
    return cls
