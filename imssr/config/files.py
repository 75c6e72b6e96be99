"""Config files: a JSON file's value with one-line errors, and a complete config read from one."""
from __future__ import annotations

import json
from typing import Any

from imssr.config.runconfig import RunConfig
from imssr.config.version import check_version
from imssr.errors import ImssrError


def read_config_file(path: str) -> Any:
    """The JSON value of a config file, with one-line errors for anything that is not JSON text."""
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise ImssrError(f"config file not found: {path}") from None
    except IsADirectoryError:
        raise ImssrError(f"config file {path} is a directory") from None
    except UnicodeDecodeError:
        raise ImssrError(f"config file {path} is not a JSON text file (it is not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise ImssrError(f"config file {path} is not valid JSON: {exc}") from None
    except RecursionError:
        raise ImssrError(f"config file {path} nests its JSON too deeply to be a config") from None


def load_config(path: str) -> RunConfig:
    """A complete config file, such as a run's ``config.json`` (fields it lacks read as the
    dataclass defaults; see :func:`imssr.presets.load_partial_config` for a file written by hand)."""
    data = read_config_file(path)
    if isinstance(data, dict):
        check_version(data, f"config {path}")
    return RunConfig.from_dict(data)
