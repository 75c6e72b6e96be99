"""The paper's settings as named presets per algorithm and task.

``make_config(algo, task)`` returns the configuration the authors ran: their
code (``duchenzhuang/dmc-disentangle``, a fork of DMC-GB) where the paper's
tables are silent, Table III and Table V where they speak.  Every value has a
recorded source (:func:`preset_settings`, ``imssr config --explain``,
docs/provenance.md).  Algorithms are pairs of an auxiliary task
and an intrinsic signal: every base ``X`` has an ``im-X`` twin (IM-SSR) and
the exploration peers ``X+rnd`` and ``X+re3``.

The modules, each name re-exported here (with the algorithm registry of :mod:`imssr.algos`):

- ``tables``: the paper's settings as ``Setting`` rows with their sources, and ``preset_settings``;
- ``build``: a run's config from a preset, a partial file or a saved run, flags and overrides.
"""
from imssr.algos import ALGOS, BASES, SIGNALS, AlgoSpec, get_algo
from imssr.presets.build import (base_config, demo_config, load_partial_config, make_config, run_config,
                                 set_field)
from imssr.presets.tables import (BASE_BETA0, BASE_SETTINGS, COMMON, CONSTANT_BETA_SCHEDULE, CONSTANT_BETA_TASKS,
                                  DEFAULT_BETA0, DEMO, INTRINSIC, INTRINSIC_LAST, NETWORKS, NORM_EPS, PAPER_BETA0, RUN,
                                  RUN_FIELDS, SCHEDULE, SCRIPT_BETA0, SIGNAL_SETTINGS, markdown_table, paper_beta0,
                                  preset_settings, show_value)
from imssr.settings import (AUTHORS, AUTHORS_CURL, AUTHORS_LOOP, AUTHORS_SIGNAL, DECAY, DMCGB, IMSSR, OFFICIAL_CURL,
                            PAPER, TABLE3, TABLE5, Setting)

__all__ = [
    "ALGOS", "AUTHORS", "AUTHORS_CURL", "AUTHORS_LOOP", "AUTHORS_SIGNAL", "AlgoSpec", "BASES", "BASE_BETA0",
    "BASE_SETTINGS", "COMMON", "CONSTANT_BETA_SCHEDULE", "CONSTANT_BETA_TASKS", "DECAY", "DEFAULT_BETA0", "DEMO",
    "DMCGB", "IMSSR", "INTRINSIC", "INTRINSIC_LAST", "NETWORKS", "NORM_EPS", "OFFICIAL_CURL", "PAPER",
    "PAPER_BETA0", "RUN", "RUN_FIELDS", "SCHEDULE", "SCRIPT_BETA0", "SIGNALS", "SIGNAL_SETTINGS", "Setting",
    "TABLE3", "TABLE5", "base_config", "demo_config", "get_algo", "load_partial_config", "make_config",
    "markdown_table", "paper_beta0", "preset_settings", "run_config", "set_field", "show_value",
]
