"""The paper's settings as named presets per algorithm and task.

``make_config(algo, task)`` returns the configuration the authors ran, every value with its source
(:func:`preset_settings`).  ``tables`` holds the settings as ``Setting`` rows; ``build`` makes a run's config from a
preset, a partial file or a saved run, flags and overrides.
"""
from imssr.algos import ALGOS, BASES, get_algo
from imssr.presets.build import demo_config, load_partial_config, make_config, run_config
from imssr.presets.tables import (DEFAULT_BETA0, NETWORKS, PAPER_BETA0, markdown_table, preset_settings, show_value)

__all__ = ["ALGOS", "BASES", "DEFAULT_BETA0", "NETWORKS", "PAPER_BETA0", "demo_config", "get_algo",
           "load_partial_config", "make_config", "markdown_table", "preset_settings", "run_config", "show_value"]
