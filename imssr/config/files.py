"""Config files: a JSON file's value with one-line errors, and a complete config read from one."""
from __future__ import annotations

from typing import Any

from imssr.config.runconfig import RunConfig
from imssr.config.version import check_version
from imssr.jsonio import read_json


def read_config_file(path: str) -> Any:
    """The JSON value of a config file, with one-line errors for anything that is not JSON text."""
    return read_json(path, "config file", "config")


def load_config(path: str) -> RunConfig:
    """A complete config file, such as a run's ``config.json`` (fields it lacks read as the
    dataclass defaults; see :func:`imssr.presets.load_partial_config` for a file written by hand)."""
    data = read_config_file(path)
    if isinstance(data, dict):
        check_version(data, f"config {path}")
    return RunConfig.from_dict(data)
